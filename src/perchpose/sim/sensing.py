"""The vehicle's senses as a real drone has them, drawn per run.

``Sensing`` holds the spreads; ``Sensing.ideal()`` is the simulation's earlier, nearly perfect
senses (a frame of latency, odometry at 50 Hz with no delay, the attitude without noise, the
renderer's exact calibration and mount). ``SensingDraw.draw`` makes one run's draws;
``SensedState`` keeps what the flight controller reports and hands it out late.

Where the default magnitudes come from:

- camera latency, capture to estimate, 40-150 ms: glass-to-estimate latency of USB (UVC)
  webcams, of FPV video through a receiver and a USB grabber, and of the Crazyflie AI deck's
  WiFi stream is typically 50-150 ms; the lower end is a global-shutter camera on a companion
  computer's CSI port. 8 ms of jitter per frame (scheduling, USB transfers);
- odometry as an onboard estimator gives it: by default velocity with 3 cm/s of white noise
  per sample, whose integral the position drifts by (beside the disturbances' slow velocity
  bias). A Crazyflie's Flow deck (PMW3901 optical flow with a VL53L1x range) fused in its
  Kalman filter gives an error correlated over the filter's time constant and growing with
  the height and the yaw rate: ``odometry="flow-deck"`` (``sim.flow_deck`` says how and from
  which figures; the vertical axis then keeps the white noise, the range sensor's). Its
  state log and an autopilot's LOCAL_POSITION_NED stream at 50-100 Hz and describe the
  vehicle 10-30 ms before they arrive;
- the setpoint uplink: a setpoint the pilot sends reaches the flight controller 4-20 ms later
  (cflib queues packets for its radio thread, which trades them with the Crazyradio over USB
  a packet per millisecond or so, each acknowledged; MAVLink over a serial or Wi-Fi link takes
  as long); drawn per run;
- the accelerometer (``acc.x``, ``acc.y`` in the Crazyflie's log, logged with the odometry):
  the BMI088's own noise (about 175 ug/sqrt(Hz), 0.01 m/s^2 over the firmware's 30 Hz filter)
  is small beside the propellers' vibration that gets through the filter, taken as 0.2 m/s^2
  per sample; a bias of up to 0.1 m/s^2 per axis (the sensor's offset left by the level
  calibration at start, and a thrust line a fraction of a degree off the sensor's z axis);
- the attitude estimate: 0.2 deg of noise per sample (a MEMS IMU's complementary or Kalman
  filter at rest) and 0-10 ms of delay;
- clocks: the camera's time stamps and the flight controller's agree to a few ms (±5 ms);
- live stamps: a live source stamps a frame when it is grabbed, and the pilot dates it from
  the grab less the camera latency the user measured (``perchpose track --camera-latency-ms``):
  a measurement that films time-coded markers on a screen knows the chain's mean latency to
  about ±10 ms (the display's own lag and its refresh are the spread), so the latency the
  pilot is given is the run's mean glass-to-grab latency plus a uniform error of ±10 ms;
- calibration: an OpenCV calibration from a few dozen views of a board leaves the focal
  length within about 1 % and the principal point within about 3 px on a 640 x 480 camera,
  and k1 within about 0.01; the camera's mount is measured to about 1 deg and 1 mm;
- the print: an office printer's scale is right to about 0.5 % (so is the target's size).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace
from statistics import NormalDist
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.control.gyro import GyroAttitude, GyroReading
from perchpose.control.history import newest_at
from perchpose.errors import SensingConfigError, require_non_negative
from perchpose.geometry import make_transform, rot_x, rot_y, rot_z
from perchpose.sim.flow_deck import FlowDeck

Array = NDArray[np.float64]

SENSINGS = ("realistic", "ideal")
ODOMETRY_ERRORS = ("white", "flow-deck")  # how the realistic odometry's error behaves
HISTORY = 256  # samples kept: seconds at the fastest rates, far beyond any delay drawn


@dataclass(frozen=True)
class Sensing:
    """Per-run spreads of the vehicle's senses (SI units; ranges are uniform, others the
    standard deviation of a normal or the half-width of a uniform, as named).

    latency_s : the camera's latency range. latency_jitter_s : per-frame jitter (the absolute
    value of a normal). odometry_hz, odometry_delay_s : the odometry's rate and age on
    arrival. odometry : how the odometry's horizontal error behaves: ``white`` (white
    ``flow_noise_mps`` per sample) or ``flow-deck`` (correlated in time, growing with height
    and yaw rate, drawn from ``flow_deck``). flow_noise_mps : white velocity noise per
    odometry sample, integrated into the position (with a flow deck, along z only).
    attitude_noise_deg : per sample. attitude_delay_s : its age on arrival.
    clock_offset_s : half-width of the camera clock's offset from the flight controller's.
    uplink_delay_s : the range of the setpoint uplink's delay. accel_noise_mps2,
    accel_bias_mps2 : the accelerometer's noise per sample and its bias's half-width.
    latency_error_s : half-width of the error of the camera latency the user measured (live
    stamps).
    focal_error, principal_point_px, k1_error : half-widths of the calibration's error.
    mount_deg, mount_mm : the camera mount's error (per axis). target_scale_error : the print's
    scale error. ``name`` ideal: none of this is drawn (``Sensing.ideal()``).
    """

    name: str = "realistic"
    latency_s: tuple[float, float] = (0.04, 0.15)
    latency_jitter_s: float = 0.008
    odometry_hz: tuple[float, float] = (50.0, 100.0)
    odometry_delay_s: tuple[float, float] = (0.01, 0.03)
    odometry: str = "white"
    flow_deck: FlowDeck = field(default_factory=FlowDeck)
    flow_noise_mps: float = 0.03
    attitude_noise_deg: float = 0.2
    attitude_delay_s: tuple[float, float] = (0.0, 0.01)
    clock_offset_s: float = 0.005
    uplink_delay_s: tuple[float, float] = (0.004, 0.02)
    accel_noise_mps2: float = 0.2
    accel_bias_mps2: float = 0.1
    latency_error_s: float = 0.01
    focal_error: float = 0.01
    principal_point_px: float = 3.0
    k1_error: float = 0.01
    mount_deg: float = 1.0
    mount_mm: float = 1.0
    target_scale_error: float = 0.005

    def __post_init__(self) -> None:
        if self.name not in SENSINGS:
            raise SensingConfigError(f"unknown sensing {self.name!r} (choose realistic or ideal)")
        ranges = (
            "latency_s",
            "odometry_hz",
            "odometry_delay_s",
            "attitude_delay_s",
            "uplink_delay_s",
        )
        for name in ranges:
            low, high = getattr(self, name)
            if not (math.isfinite(low) and math.isfinite(high) and 0 <= low <= high):
                raise SensingConfigError(f"{name} must be 0 <= low <= high, got {low}, {high}")
        if self.odometry not in ODOMETRY_ERRORS:
            raise SensingConfigError(
                f"unknown odometry {self.odometry!r} (choose {' or '.join(ODOMETRY_ERRORS)})"
            )
        if self.odometry_hz[0] <= 0:
            raise SensingConfigError("odometry_hz must be positive")
        spreads = (
            "latency_jitter_s",
            "flow_noise_mps",
            "attitude_noise_deg",
            "accel_noise_mps2",
            "accel_bias_mps2",
            "clock_offset_s",
            "latency_error_s",
            "focal_error",
            "principal_point_px",
            "k1_error",
            "mount_deg",
            "mount_mm",
            "target_scale_error",
        )
        require_non_negative(self, spreads, SensingConfigError)

    @property
    def is_ideal(self) -> bool:
        return self.name == "ideal"

    @staticmethod
    def ideal() -> Sensing:
        """The simulation's earlier senses: nothing drawn here (the latency is
        ``PerchSetup.latency_frames``, the odometry ``PerchSetup.odometry_hz`` with the
        disturbances' noise and drift)."""
        return Sensing(name="ideal")

    def with_latency(self, latency_s: float) -> Sensing:
        """These senses with the camera's latency fixed (its jitter kept)."""
        return replace(self, latency_s=(latency_s, latency_s))

    @property
    def max_latency_s(self) -> float:
        """The longest latency drawn, jitter aside."""
        return self.latency_s[1]


@dataclass(frozen=True)
class SensingDraw:
    """One run's senses: the camera's latency, the odometry's rate and delay, the attitude's
    delay, the clock offset, the calibration the estimator is given (``camera``), the mount's
    error ``T_true_believed`` (the true ``T_body_camera`` is the believed one times it) and the
    print's scale. ``latency_configured_s``: the camera latency the pilot is given with live
    stamps (NaN until the flight sets it: it depends on the frame rate). ``uplink_delay_s``:
    the setpoint uplink's delay (the flight draws it from a generator of its own)."""

    latency_s: float
    odometry_hz: float
    odometry_delay_s: float
    attitude_delay_s: float
    clock_offset_s: float
    camera: CameraModel
    T_true_believed: Array = field(repr=False)
    target_scale: float
    latency_configured_s: float = math.nan
    uplink_delay_s: float = 0.0

    @staticmethod
    def draw(sensing: Sensing, camera: CameraModel, rng: np.random.Generator) -> SensingDraw:
        """Draws for one run from ``rng``; ``camera`` is the true camera."""
        s = sensing

        def spread(half: float, n: int | None = None) -> Array:
            return np.asarray(rng.uniform(-half, half, n), np.float64)

        K = np.array(camera.K, np.float64)
        focal = 1.0 + float(spread(s.focal_error))
        K[0, 0] *= focal
        K[1, 1] *= focal
        K[0, 2] += float(spread(s.principal_point_px))
        K[1, 2] += float(spread(s.principal_point_px))
        dist = np.array(camera.dist, np.float64)
        if camera.model == "plumb_bob":
            dist[0] += float(spread(s.k1_error))
        calibrated = CameraModel(
            K, dist, camera.width_px, camera.height_px, camera.model, f"{camera.name} (calibrated)"
        )
        roll, pitch, yaw = np.radians(spread(s.mount_deg, 3))
        shift = spread(s.mount_mm, 3) / 1000.0
        mount = make_transform(rot_z(float(yaw)) @ rot_y(float(pitch)) @ rot_x(float(roll)), shift)
        return SensingDraw(
            latency_s=float(rng.uniform(*s.latency_s)),
            odometry_hz=float(rng.uniform(*s.odometry_hz)),
            odometry_delay_s=float(rng.uniform(*s.odometry_delay_s)),
            attitude_delay_s=float(rng.uniform(*s.attitude_delay_s)),
            clock_offset_s=float(spread(s.clock_offset_s)),
            camera=calibrated,
            T_true_believed=mount,
            target_scale=1.0 + float(spread(s.target_scale_error)),
        )


class Sample(NamedTuple):
    """One sample the flight controller made: when, and what it said."""

    t_s: float
    R_world_body: Array
    p_m: Array
    v_mps: Array
    f_body_mps2: Array | None = None  # the accelerometer
    gyro_dps: Array | None = None  # the gyro (body rates, deg/s), logged with the attitude


class SensedState:
    """What the flight controller reports, as it reaches the pilot: each sample stored when it
    is made (the attitude with its noise), handed out once it is its delay old."""

    def __init__(self, attitude_delay_s: float, odometry_delay_s: float) -> None:
        self.attitude_delay_s = attitude_delay_s
        self.odometry_delay_s = odometry_delay_s
        self._samples: deque[tuple[float, Sample]] = deque(maxlen=HISTORY)
        self.gyro = GyroAttitude()  # integrated as the samples arrive, as a link would
        self._gyro_through_s = -math.inf

    def record(
        self,
        t_s: float,
        R_world_body: Array,
        p_m: Array,
        v_mps: Array,
        f_body_mps2: Array | None = None,
        gyro_dps: Array | None = None,
    ) -> None:
        """A sample the flight controller made at ``t_s`` (``f_body_mps2``: its
        accelerometer's, ``gyro_dps`` its gyro's, where it logs them)."""
        sample = Sample(
            t_s,
            R_world_body,
            np.array(p_m, np.float64),
            np.array(v_mps, np.float64),
            None if f_body_mps2 is None else np.array(f_body_mps2, np.float64),
            None if gyro_dps is None else np.array(gyro_dps, np.float64),
        )
        self._samples.append((t_s, sample))

    def _attitude_sample(self, t_s: float) -> Sample:
        return newest_at(self._samples, t_s - self.attitude_delay_s)

    def _odometry_sample(self, t_s: float) -> Sample:
        return newest_at(self._samples, t_s - self.odometry_delay_s)

    def attitude(self, t_s: float) -> Array:
        """The attitude that has reached the pilot at ``t_s``."""
        return self._attitude_sample(t_s).R_world_body

    def ages(self, t_s: float) -> tuple[float, float]:
        """How old, at ``t_s``, the attitude and the odometry the pilot has are (from when
        the flight controller made them)."""
        return t_s - self._attitude_sample(t_s).t_s, t_s - self._odometry_sample(t_s).t_s

    def odometry(self, t_s: float) -> tuple[Array, Array]:
        """The position and velocity that have reached the pilot at ``t_s``."""
        sample = self._odometry_sample(t_s)
        return sample.p_m, sample.v_mps

    def gyro_reading(self, t_s: float) -> GyroReading | None:
        """The gyro integrated over every sample that has reached the pilot by ``t_s`` (with
        the attitude), in the order they were made; None before the first."""
        arrived_s = t_s - self.attitude_delay_s
        fresh = []
        for made_s, sample in reversed(self._samples):
            if made_s <= self._gyro_through_s:
                break
            if made_s <= arrived_s:
                fresh.append(sample)
        for sample in reversed(fresh):
            if sample.gyro_dps is not None:
                self.gyro.add(sample.t_s, np.radians(sample.gyro_dps))
            self._gyro_through_s = sample.t_s
        return self.gyro.reading()

    def specific_force(self, t_s: float) -> Array | None:
        """The accelerometer's sample that has reached the pilot at ``t_s`` (it comes with the
        odometry)."""
        return self._odometry_sample(t_s).f_body_mps2


class Accelerometer:
    """The accelerometer's errors over one run: a bias drawn once per axis, noise per sample."""

    def __init__(self, noise_mps2: float, bias_mps2: float, rng: np.random.Generator) -> None:
        self.noise_mps2 = noise_mps2
        self.bias_mps2 = np.asarray(rng.uniform(-bias_mps2, bias_mps2, 3), np.float64)
        self._rng = rng

    def read(self, f_body_mps2: Array) -> Array:
        """A sample of the true specific force ``f_body_mps2`` (body frame)."""
        noise = self._rng.normal(0.0, self.noise_mps2, 3) if self.noise_mps2 > 0 else 0.0
        read: Array = np.asarray(f_body_mps2, np.float64) + self.bias_mps2 + noise
        return read


def noisy_attitude(R_world_body: Array, noise_deg: float, rng: np.random.Generator) -> Array:
    """``R_world_body`` turned by a small random rotation (``noise_deg`` per axis)."""
    if noise_deg <= 0:
        return R_world_body
    rx, ry, rz = np.radians(rng.normal(0.0, noise_deg, 3))
    turned: Array = R_world_body @ rot_z(float(rz)) @ rot_y(float(ry)) @ rot_x(float(rx))
    return turned


def mean_glass_to_grab_s(
    latency_s: float, jitter_s: float, fps: float, late_probability: float
) -> float:
    """The mean time from a frame's capture to its grab in the simulation: the latency plus
    the absolute value of a normal jitter, up to the next frame's tick (at least one frame),
    and a frame more with ``late_probability``; what a user's latency measurement averages.
    The jitter's half-normal is integrated on its quantiles (no draw: the run's random
    streams stay as they were)."""
    quantiles = (np.arange(200) + 0.5) / 200.0
    jitters = [jitter_s * NormalDist().inv_cdf(0.5 + 0.5 * q) for q in quantiles]
    frames = [max(1, math.ceil((latency_s + j) * fps - 1e-9)) for j in jitters]
    return (float(np.mean(frames)) + late_probability) / fps
