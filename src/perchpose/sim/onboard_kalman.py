"""The Crazyflie firmware's Kalman estimator flying the simulated vehicle.

``perchpose perch --onboard-estimator crazyflie-kalman`` puts the firmware's own Kalman core
(``kalman_core.c`` with its flow and range measurement models ``mm_flow.c`` and ``mm_tof.c``,
from the ``cffirmware`` module: GPL-3.0, an optional extra the user builds, imported only
here and only when asked for) in place of the model's onboard estimate, which is the truth
plus white noise. Its state is what the vehicle's own loops fly (the velocity and the
attitude), the odometry and attitude the pilot gets over the link, and the height.

It runs as the firmware's estimator task runs it, a tick per millisecond of the main loop:
each tick the IMU's sample is accumulated (``axis3fSubSamplerAccumulate``: the accelerometer
in g, the gyro in deg/s), at 100 Hz the accumulated samples are averaged and the state
predicted (``kalmanCorePredict``), each tick the process noise is added, the flow and range
samples are fused when the deck delivers them, and the state is finalized. Its senses
(``KalmanSenses`` says what each default rests on):

- the IMU (a BMI088): gyro and accelerometer with white noise per sample (the sensor's noise
  density and the propellers' vibration through the firmware's filters) and a bias drawn per
  run (what the firmware's start-up calibration leaves), the accelerometer low-passed at
  30 Hz as the firmware filters it (``Quadrotor.specific_force_body_mps2``);
- the Flow deck v2's PMW3901 at 100 Hz: the pixels the floor moved past its 35 x 35 window
  over its true aperture (42 degrees, times a lens tolerance drawn per run; the firmware's
  model assumes ``2 sin(21 deg)``, 2.2 % less), counted in the sensor's integer units (a tenth
  of a pixel, ``FLOW_RESOLUTION``; the motion under a count carries to the next read) with
  ``FlowDeck.pixel_noise_px`` of noise per read and extra under yaw
  (``FlowDeck.rotation_blur``); the deck driver's fixed ``stdDevX`` of 2 counts; counts of
  100 or more dropped as the driver drops them;
- the VL53L1x range at 40 Hz (the deck driver's period): the distance along the body's z axis
  to the floor with noise of 5 mm plus 1 % of the range, readings beyond 4 m dropped; the
  driver's spread, which grows from 5 mm at 2.5 m exponentially to 0.2 m at 4 m.

The vertical axis thus comes from the range and the accelerometer, the horizontal velocity
from the flow, the yaw from the gyro alone (it drifts with the gyro's bias).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import SensingConfigError, require_non_negative
from perchpose.geometry import rotation_from_quaternion
from perchpose.sim.flow_deck import APERTURE_RAD, EDGE_PX, WINDOW_PX, FlowDeck
from perchpose.sim.quadrotor import GRAVITY_MPS2, Quadrotor, mat3

Array = NDArray[np.float64]
Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]

ONBOARD_ESTIMATORS = ("model", "crazyflie-kalman")
TICK_MS = 1  # the firmware's main loop: 1 kHz
PREDICT_EVERY_MS = 10  # the estimator's prediction: 100 Hz
FLOW_EVERY_MS = 10  # the PMW3901's reads: 100 Hz
RANGE_EVERY_MS = 25  # the VL53L1x's reads: 40 Hz
FLOW_RESOLUTION = 0.1  # pixels per count of the PMW3901's registers (the firmware's factor)
FLOW_STD_COUNTS = 2.0  # the deck driver's fixed spread of a flow read (flowStdFixed)
FLOW_OUTLIER_COUNTS = 100  # the deck driver drops reads this large
RANGE_MAX_M = 4.0  # the VL53L1x's long-distance mode
IGNORED_STD_RAD = 1000.0  # an attitude measurement's spread that leaves the attitude alone
SETTLE_MS = 2000  # the estimator converges this long on the hovering vehicle before a run
# the range driver's spread, a * (1 + exp(c (d - d_a))) with c = ln(b / a) / (d_b - d_a):
# (d_a, a), (d_b, b)
RANGE_STD_AT = ((2.5, 0.0025), (4.0, 0.2))


@dataclass(frozen=True)
class KalmanSenses:
    """The IMU's and the range sensor's errors (the flow's are ``FlowDeck``'s).

    gyro_noise_dps : per 1 kHz sample: the BMI088's 0.014 deg/s/sqrt(Hz) over its 116 Hz
    bandwidth is 0.15 deg/s; the propellers' vibration through the firmware's gyro filter
    doubles it. gyro_bias_dps : half-width of the bias per axis left by the firmware's start-up
    calibration (it averages the gyro at rest) and its drift over a flight. accel_noise_mps2 :
    per sample, the vibration through the 30 Hz filter (``Sensing.accel_noise_mps2``'s figure).
    accel_bias_mps2 : half-width per axis: the BMI088's offset after the level calibration and
    a thrust line a fraction of a degree off. range_noise_m, range_noise_share : the VL53L1x's
    ranging error, a constant plus a share of the range. lens_tolerance : half-width of the
    flow lens's aperture error, drawn per run."""

    gyro_noise_dps: float = 0.3
    gyro_bias_dps: float = 0.1
    accel_noise_mps2: float = 0.2
    accel_bias_mps2: float = 0.1
    range_noise_m: float = 0.005
    range_noise_share: float = 0.01
    lens_tolerance: float = 0.01

    def __post_init__(self) -> None:
        names = (
            "gyro_noise_dps",
            "gyro_bias_dps",
            "accel_noise_mps2",
            "accel_bias_mps2",
            "range_noise_m",
            "range_noise_share",
            "lens_tolerance",
        )
        require_non_negative(self, names, SensingConfigError)


def check_onboard_estimator(name: str) -> None:
    """Refuse an onboard estimator this package does not fly."""
    if name not in ONBOARD_ESTIMATORS:
        raise SensingConfigError(
            f"unknown onboard estimator {name!r} (choose {', '.join(ONBOARD_ESTIMATORS)})"
        )


def range_std_m(distance_m: float) -> float:
    """The spread the Flow deck's range driver gives a reading at ``distance_m``."""
    (d0, s0), (d1, s1) = RANGE_STD_AT
    rate = math.log(s1 / s0) / (d1 - d0)
    return s0 * (1.0 + math.exp(rate * (distance_m - d0)))


class CrazyflieKalman:
    """The firmware's Kalman core on one run's senses, started at the vehicle's true place
    and heading; ``advance`` after each physics step. ``velocity`` (world frame, m/s),
    ``position`` (m) and ``attitude`` (``R_world_body``) are its estimate; ``flying``: whether
    the firmware takes the vehicle as flying (its motors on)."""

    def __init__(
        self,
        fw: ModuleType,
        senses: KalmanSenses,
        deck: FlowDeck,
        rng: np.random.Generator,
        vehicle: Quadrotor,
    ) -> None:
        self._fw = fw
        self.senses = senses
        self.deck = deck
        self._rng = rng
        self.gyro_bias_dps: Array = rng.uniform(-senses.gyro_bias_dps, senses.gyro_bias_dps, 3)
        self.accel_bias_mps2: Array = rng.uniform(
            -senses.accel_bias_mps2, senses.accel_bias_mps2, 3
        )
        self.aperture_rad = APERTURE_RAD * (
            1.0 + float(rng.uniform(-senses.lens_tolerance, senses.lens_tolerance))
        )
        self.flying = True
        self._params = fw.kalmanCoreParams_t()
        fw.kalmanCoreDefaultParams(self._params)
        p = vehicle.p_m
        self._params.initialX, self._params.initialY, self._params.initialZ = (float(v) for v in p)
        self._params.initialYaw = float(vehicle.yaw_rad)
        self._core = fw.kalmanCoreData_t()
        self._now_ms = 0
        fw.kalmanCoreInit(self._core, self._params, self._now_ms)
        self._acc = fw.Axis3fSubSampler_t()
        self._gyro = fw.Axis3fSubSampler_t()
        fw.axis3fSubSamplerInit(self._acc, GRAVITY_MPS2)
        fw.axis3fSubSamplerInit(self._gyro, math.radians(1.0))
        self._acc_latest = fw.Axis3f()
        self._gyro_latest = fw.Axis3f()
        self._flow = fw.flowMeasurement_t()
        self._flow.stdDevX = self._flow.stdDevY = FLOW_STD_COUNTS
        self._range = fw.tofMeasurement_t()
        self._state = fw.state_t()
        self._pose = fw.poseMeasurement_t()
        self.external_positions = 0  # fused
        self._next_predict_ms = PREDICT_EVERY_MS
        self._flow_px = [0.0, 0.0]  # the floor's motion past the window since the last read
        self._flow_carry = [0.0, 0.0]  # counts' fractions the sensor carries to its next read
        self._flow_blur_px2 = 0.0  # the yaw's smear over the read, squared
        self._pending_s = 0.0
        self.velocity: Vec3 = (0.0, 0.0, 0.0)
        self.position: Vec3 = (float(p[0]), float(p[1]), float(p[2]))
        self.attitude: Mat3 = mat3(vehicle.R_world_body)
        self.flow_reads = 0  # reads fused
        self.range_reads = 0
        self._externalize()

    def settle(self, vehicle: Quadrotor) -> None:
        """Run ``SETTLE_MS`` on the vehicle as it is (hovering, still) without moving it, so
        the filter's spreads have converged when the run starts."""
        dt_s = TICK_MS / 1000.0
        for _ in range(SETTLE_MS // TICK_MS):
            self.advance(dt_s, vehicle)

    def advance(self, dt_s: float, vehicle: Quadrotor) -> None:
        """The estimator through ``dt_s`` of the vehicle's true motion (whole milliseconds)."""
        self._pending_s += dt_s
        ticks = int(self._pending_s * 1000.0 + 1e-6)
        if ticks <= 0:
            return
        self._pending_s -= ticks / 1000.0
        self._see_floor(ticks * TICK_MS / 1000.0, vehicle)
        fw = self._fw
        for _ in range(ticks):
            self._now_ms += TICK_MS
            now = self._now_ms
            self._imu_sample(vehicle)
            if now >= self._next_predict_ms:
                acc = fw.axis3fSubSamplerFinalize(self._acc)
                gyro = fw.axis3fSubSamplerFinalize(self._gyro)
                fw.kalmanCorePredict(self._core, self._params, acc, gyro, now, self.flying)
                self._next_predict_ms = now + PREDICT_EVERY_MS
            fw.kalmanCoreAddProcessNoise(self._core, self._params, now)
            if now % FLOW_EVERY_MS == 0:
                self._flow_read()
            if now % RANGE_EVERY_MS == 0:
                self._range_read(vehicle)
            fw.kalmanCoreFinalize(self._core)
        self._externalize()

    @property
    def velocity_mps(self) -> Array:
        return np.array(self.velocity)

    @property
    def position_m(self) -> Array:
        return np.array(self.position)

    @property
    def R_world_body(self) -> Array:
        return np.array(self.attitude)

    @property
    def gyro_dps(self) -> Array:
        """The IMU's latest gyro sample (body rates with their bias and noise, deg/s): what
        the firmware logs as ``gyro.x/y/z``."""
        g = self._gyro_latest
        return np.array([g.x, g.y, g.z], np.float64)

    def _imu_sample(self, vehicle: Quadrotor) -> None:
        s, rng = self.senses, self._rng
        w_dps = np.degrees(vehicle.omega_rad_s) + self.gyro_bias_dps
        w_dps = w_dps + rng.normal(0.0, s.gyro_noise_dps, 3)
        f = vehicle.specific_force_body_mps2 + self.accel_bias_mps2
        f_g = (f + rng.normal(0.0, s.accel_noise_mps2, 3)) / GRAVITY_MPS2
        g, a = self._gyro_latest, self._acc_latest
        g.x, g.y, g.z = (float(v) for v in w_dps)
        a.x, a.y, a.z = (float(v) for v in f_g)
        self._fw.axis3fSubSamplerAccumulate(self._gyro, g)
        self._fw.axis3fSubSamplerAccumulate(self._acc, a)

    def _see_floor(self, dt_s: float, vehicle: Quadrotor) -> None:
        """The floor's motion past the flow sensor's window over ``dt_s`` (pixels), as the
        firmware's model of it has it, with the lens's true aperture."""
        R = vehicle.R_world_body
        v_body = R.T @ vehicle.v_mps
        wx, wy, wz = (float(w) for w in vehicle.omega_rad_s)
        r22 = float(R[2, 2])
        h = max(self.deck.min_height_m, float(vehicle.p_m[2]))
        per_rad = dt_s * WINDOW_PX / self.aperture_rad
        self._flow_px[0] += per_rad * (float(v_body[0]) * r22 / h - wy)
        self._flow_px[1] += per_rad * (float(v_body[1]) * r22 / h + wx)
        smear_px = EDGE_PX * abs(wz) * dt_s
        self._flow_blur_px2 += (self.deck.rotation_blur * smear_px) ** 2

    def _flow_read(self) -> None:
        sigma_px = math.sqrt(self.deck.pixel_noise_px**2 + self._flow_blur_px2)
        counts = []
        for axis in range(2):
            exact = self._flow_px[axis] / FLOW_RESOLUTION + self._flow_carry[axis]
            whole = round(exact)
            self._flow_carry[axis] = exact - whole
            counts.append(round(exact + float(self._rng.normal(0.0, sigma_px / FLOW_RESOLUTION))))
        self._flow_px = [0.0, 0.0]
        self._flow_blur_px2 = 0.0
        if max(abs(c) for c in counts) >= FLOW_OUTLIER_COUNTS:
            return
        m = self._flow
        m.dpixelx, m.dpixely = float(counts[0]), float(counts[1])
        m.dt = FLOW_EVERY_MS / 1000.0
        m.timestamp = self._now_ms
        self._fw.kalmanCoreUpdateWithFlow(self._core, m, self._gyro_latest)
        self.flow_reads += 1

    def _range_read(self, vehicle: Quadrotor) -> None:
        r22 = float(vehicle.R_world_body[2, 2])
        if r22 <= 0.1:
            return
        distance = float(vehicle.p_m[2]) / r22
        s = self.senses
        distance += float(self._rng.normal(0.0, s.range_noise_m + s.range_noise_share * distance))
        if not 0.0 < distance <= RANGE_MAX_M:
            return
        m = self._range
        m.distance = distance
        m.stdDev = range_std_m(distance)
        m.timestamp = self._now_ms
        self._fw.kalmanCoreUpdateWithTof(self._core, m)
        self.range_reads += 1

    def external_position(self, p_m: Array, std_m: float) -> None:
        """Fuse an external position (world frame, m) as the firmware fuses cflib's
        ``send_extpos``: three scalar updates of the position with spread ``std_m``. The
        bindings carry ``mm_pose.c``, not ``mm_position.c``: its position updates are the
        same, and its attitude part is given the filter's own attitude with a spread of
        ``IGNORED_STD_RAD``, which leaves the attitude as it is."""
        fw = self._fw
        m = self._pose
        m.x, m.y, m.z = (float(v) for v in p_m)
        q = self._state.attitudeQuaternion
        m.quat.x, m.quat.y, m.quat.z, m.quat.w = q.x, q.y, q.z, q.w
        m.stdDevPos = float(std_m)
        m.stdDevQuat = IGNORED_STD_RAD
        fw.kalmanCoreUpdateWithPose(self._core, m)
        self.external_positions += 1
        self._externalize()

    def _externalize(self) -> None:
        st = self._state
        self._fw.kalmanCoreExternalizeState(self._core, st, self._acc_latest)
        p, v, q = st.position, st.velocity, st.attitudeQuaternion
        self.position = (float(p.x), float(p.y), float(p.z))
        self.velocity = (float(v.x), float(v.y), float(v.z))
        self.attitude = mat3(rotation_from_quaternion(q.w, q.x, q.y, q.z))
        if not all(math.isfinite(x) for x in self.position + self.velocity):
            raise SensingConfigError("the firmware's Kalman estimate is not finite")
