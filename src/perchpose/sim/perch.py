"""Closed-loop perching in simulation: the vehicle in wind, the camera in the loop, the
estimator and the perching pilot that also flies the Crazyflie; only the scoring reads the true
pose.

Each run draws, from its seed: the start, the wind's direction and its gusts, the vehicle's
disturbances (``perchpose.sim.disturbances``) and the camera's noise, drops and latency. The
world (start, wind, vehicle) comes from one generator and the camera from another, so the same
seed flies the same world with every estimator.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.control import (
    ControllerSettings,
    PerchingController,
    PerchingPilot,
    Phase,
    PilotSettings,
    PilotState,
    SenseAges,
)
from perchpose.control.gyro import GyroReading
from perchpose.errors import VehicleConfigError
from perchpose.estimator import PerchingEstimator
from perchpose.fusion.base import stage_of
from perchpose.geometry import invert_transform, make_transform, rot_z, tilt_rad, yaw_rad
from perchpose.sim.contact import (
    MAGNET,
    Contact,
    ContactRules,
    Magnet,
    PlateContact,
    PlateForces,
    PlateSurface,
    tilt_deg,
)
from perchpose.sim.disturbances import Disturbances, OdometryModel, VehicleDraw
from perchpose.sim.faults import LEVEL_AFTER_S, MOTORS_OFF_AFTER_S, Fault, check_faults
from perchpose.sim.firmware import FirmwareQuadrotor, check_flight_controller, load_firmware
from perchpose.sim.flow_deck import FlowDeckError
from perchpose.sim.onboard_kalman import CrazyflieKalman, KalmanSenses, check_onboard_estimator
from perchpose.sim.quadrotor import (
    AttitudeHold,
    Hold,
    OnboardGains,
    PositionHold,
    Quadrotor,
    QuadrotorParams,
    vec3,
)
from perchpose.sim.render import ImageQuality, Renderer
from perchpose.sim.scenarios import markers_in_view
from perchpose.sim.sensing import (
    Accelerometer,
    SensedState,
    Sensing,
    SensingDraw,
    mean_glass_to_grab_s,
    noisy_attitude,
)
from perchpose.sim.wind import DrydenWind, WindLevel, wind_level
from perchpose.target import TargetSpec
from perchpose.values import Estimate

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

ESTIMATORS = ("paper", "outer", "inner", "covariance", "truth")
# how frames are stamped: as the live sources stamp them (the grab, less the camera latency
# the user measured), or with their true capture time (the simulation's earlier clock)
STAMPS = ("live", "exact")
# how a contact ends a run: the flight goes on through it until the magnet holds the vehicle
# with its motors stopped (or it does not), or the run is scored at the first touch by rules
CONTACT_MODES = ("hold", "first-touch")
# makes the simulated vehicle: parameters, start position, heading, onboard gains
Plant = Callable[[QuadrotorParams, Array, float, OnboardGains], Quadrotor]
REASONS = (
    "perched",
    "off-centre",
    "too-fast",
    "sideways",
    "tilted",
    "rotor-strike",
    "timeout",
    "lost",
    "gave-up",
    "crash",
    "fell",
    "not-seated",
    "not-stopped",
)
CONTACT_RADIUS_MM = ContactRules().max_offset_mm  # the paper's 25 mm magnet
MAX_TILT_DEG = 60.0  # beyond this the vehicle has flipped: a crash
REST_Z_M = 0.025  # the body's centre above the floor when it stands on its feet
FLOOR_CRASH_MPS = 1.0  # meeting the floor faster than this is a crash, not a landing
FALL_M = 0.05  # motors stopped higher than this above what the vehicle rests on: it falls
R_WORLD_TARGET = np.diag([1.0, -1.0, -1.0])  # printed face down, x along world x
OFFSET_AT_S = 3.0  # the flight time at which the time-offset estimate is scored
HOLD_S = 1.0  # a perch is judged this long after the motors stopped against the plate
AT_PLATE_M = 0.005  # motors stopped with the gear this near the plate: stopped against it
FELL_M = 0.01  # the gear this far below the plate after the motors stopped there: it fell
STILL_MPS = 0.02  # a held vehicle moves slower than this
# the flight controller's fused height: its range readings (40 Hz) low-passed over this time,
# which leaves sqrt(a / (2 - a)) of a reading's spread, a = 1 - exp(-0.025 s / tau)
FUSED_HEIGHT_TAU_S = 0.2
FUSED_HEIGHT_SHARE = 0.25


class OffsetReport(NamedTuple):
    """A time-offset estimate as a run reports it (s): the estimate, its spread, and the true
    offset (each frame's true capture time less its stamp, averaged over the frames the pilot
    got within the estimate's window)."""

    offset_s: float
    sigma_s: float
    true_s: float


NO_OFFSET = OffsetReport(math.nan, math.nan, math.nan)


@dataclass(frozen=True)
class PerchSetup:
    """Everything a perching run needs besides its seed."""

    camera: CameraModel
    target: TargetSpec
    vehicle: QuadrotorParams = field(default_factory=QuadrotorParams)
    onboard: OnboardGains = field(default_factory=OnboardGains)
    controller: ControllerSettings = field(default_factory=ControllerSettings)
    pilot: PilotSettings = field(default_factory=PilotSettings)
    estimator: str = "paper"
    plate_z_m: float = 2.0
    start_below_m: tuple[float, float] = (0.6, 1.5)
    start_lateral_fraction: float = 0.12
    fps: float = 30.0
    latency_frames: int = 1
    drop_probability: float = 0.05
    physics_hz: float = 500.0
    odometry_hz: float = 50.0
    duration_s: float = 20.0
    hover_s: float = 3.0
    wind: str = "none"
    wind_mps: float | None = None
    gust_mps: float | None = None
    disturbances: Disturbances = field(default_factory=Disturbances)
    ceiling_effect: bool = True
    supersample: int = 1
    quality: ImageQuality = field(default_factory=ImageQuality)
    contact: ContactRules = field(default_factory=ContactRules)
    sensing: Sensing = field(default_factory=Sensing.ideal)
    stamps: str = "live"
    faults: tuple[str, ...] = ()
    flight_controller: str = "model"
    onboard_estimator: str = "model"
    contact_mode: str = "hold"
    magnet: Magnet = field(default_factory=Magnet)
    surface: PlateSurface = field(default_factory=PlateSurface)

    def __post_init__(self) -> None:
        check_flight_controller(self.flight_controller)
        check_onboard_estimator(self.onboard_estimator)
        if self.stamps not in STAMPS:
            raise VehicleConfigError(f"unknown stamps {self.stamps!r} (choose live or exact)")
        check_faults(self.faults)
        if self.contact_mode not in CONTACT_MODES:
            raise VehicleConfigError(
                f"unknown contact {self.contact_mode!r} (choose {' or '.join(CONTACT_MODES)})"
            )
        stalls = [f for f in self.faults if f in ("odometry-stall", "attitude-stall")]
        if stalls and self.sensing.is_ideal:
            raise VehicleConfigError(
                f"{stalls[0]} needs realistic senses (ideal ones reach the pilot at once)"
            )
        if self.estimator not in ESTIMATORS:
            raise VehicleConfigError(
                f"unknown estimator {self.estimator!r} (choose {', '.join(ESTIMATORS)})"
            )
        self.wind_level  # noqa: B018  (checks the level, or the speeds given instead)
        low, high = self.start_below_m
        if not 0 < low <= high:
            raise VehicleConfigError("start_below_m must be 0 < low <= high")
        if not (self.fps > 0 and self.physics_hz >= self.fps and self.duration_s > 0):
            raise VehicleConfigError("need fps > 0, physics_hz >= fps and duration_s > 0")
        if not (math.isfinite(self.hover_s) and self.hover_s >= 0):
            raise VehicleConfigError(f"hover_s must be a time of 0 s or more, got {self.hover_s}")
        if not 0 <= self.odometry_hz <= self.physics_hz:
            raise VehicleConfigError("need 0 <= odometry_hz <= physics_hz")
        if abs(self.controller.camera_period_s - 1.0 / self.fps) > 1e-9:
            raise VehicleConfigError("the controller's camera_period_s must be 1 / fps")
        if self.latency_frames < 0:
            raise VehicleConfigError(f"latency_frames must be >= 0, got {self.latency_frames}")
        if abs(self.controller.camera_latency_s - self.latency_s) > 1e-9:
            what = "latency_frames / fps" if self.sensing.is_ideal else "the sensing's longest"
            raise VehicleConfigError(
                f"the controller's camera_latency_s must be {what} latency "
                f"({self.latency_s:.4f} s); PerchSetup.with_timing or with_sensing sets both"
            )
        self.check_start_box()

    @property
    def to_motor_stop(self) -> bool:
        """Runs go on through a landing until the motors stop (with faults); otherwise they
        end where a landing starts, as the campaigns before faults measured them."""
        return bool(self.faults)

    @property
    def latency_s(self) -> float:
        """The camera's latency, capture to estimate, before jitter (with realistic senses the
        longest drawn)."""
        if self.sensing.is_ideal:
            return self.latency_frames / self.fps
        return self.sensing.max_latency_s

    @property
    def latency_range_s(self) -> tuple[float, float]:
        """The range the camera's latency is drawn from (one value with ideal senses)."""
        if self.sensing.is_ideal:
            return (self.latency_s, self.latency_s)
        return self.sensing.latency_s

    @property
    def latency_label(self) -> str:
        """The latency a campaign cell flies, in ms: ``33``, or a drawn range ``40-150``."""
        low, high = (round(v * 1000.0) for v in self.latency_range_s)
        return f"{low}" if low == high else f"{low}-{high}"

    def with_sensing(self, sensing: Sensing) -> PerchSetup:
        """This setup with other senses, the controller told of their longest latency."""
        latency_s = self.latency_frames / self.fps if sensing.is_ideal else sensing.max_latency_s
        controller = replace(self.controller, camera_latency_s=latency_s)
        return replace(self, sensing=sensing, controller=controller)

    def with_timing(self, fps: float, latency_frames: int) -> PerchSetup:
        """This setup with another frame rate and latency, the controller told of both."""
        latency_s = latency_frames / fps if self.sensing.is_ideal else self.latency_s
        controller = replace(self.controller, camera_period_s=1.0 / fps, camera_latency_s=latency_s)
        return replace(self, fps=fps, latency_frames=latency_frames, controller=controller)

    @property
    def wind_level(self) -> WindLevel:
        """The named level, with ``wind_mps`` and ``gust_mps`` in place of its values where
        given."""
        level = wind_level(self.wind)
        return WindLevel(
            level.mean_mps if self.wind_mps is None else self.wind_mps,
            level.turbulence_sigma_mps if self.gust_mps is None else self.gust_mps,
        )

    @property
    def physics_steps(self) -> int:
        """The physics steps of a whole run."""
        return int(round(self.duration_s * self.physics_hz))

    def renderer(self) -> Renderer[TargetSpec]:
        """The renderer of this setup's frames (sensor noise from a bank: see ``Renderer``)."""
        return Renderer(self.camera, self.target, supersample=self.supersample, noise_bank=True)

    @property
    def T_world_target(self) -> Array:
        """The target on the underside of the plate, facing down."""
        return make_transform(R_WORLD_TARGET, np.array([0.0, 0.0, self.plate_z_m]))

    def T_world_camera(self, p_m: Array, R_world_body: Array) -> Array:
        """Camera pose for a body pose."""
        return make_transform(R_world_body, p_m) @ self.controller.T_body_camera

    def check_start_box(self) -> None:
        """Raise if the camera cannot see the outer marker from every corner of the start box."""
        for below in self.start_below_m:
            lateral = self.start_lateral_fraction * below
            for dx in (-lateral, lateral):
                for dy in (-lateral, lateral):
                    for yaw in np.linspace(-math.pi, math.pi, 8, endpoint=False):
                        p = np.array([dx, dy, self.plate_z_m - below])
                        R = rot_z(float(yaw))
                        T = invert_transform(self.T_world_camera(p, R)) @ self.T_world_target
                        if not markers_in_view(self.camera, self.target, T)[0]:
                            raise VehicleConfigError(
                                f"camera {self.camera.name!r} cannot see the target from the "
                                f"start box corner ({dx:+.2f}, {dy:+.2f}) m, {below:.2f} m "
                                "below it: shrink the box or use a wider camera"
                            )


@dataclass(frozen=True)
class PerchResult:
    """One run. ``reason``: one of ``REASONS``. ``tries``: final climbs the controller backed
    off from. ``wind_direction_rad``: where this run's mean wind blew to. ``contact``: the
    first contact with the plate (None: none). ``senses``: the run's draw of the vehicle's
    senses (None: ideal). ``fault``: the fault injected (None: none). With faults the run goes
    on through a landing until the motors stop: ``motor_stop_height_m`` is then the height
    above whatever the vehicle rests on (0 perched or on the floor; NaN: they never stopped),
    ``pilot_states`` the pilot's states with the times it entered them
    (``perching@0.03;lost@5.10``), ``max_setpoint_gap_s`` the longest the vehicle went
    without a setpoint while the pilot flew it. ``time_offset`` and ``time_offset_end``: the
    controller's estimate of the camera-to-vehicle time offset after ``OFFSET_AT_S`` of
    flight and at the run's end, each with the truth over the frames it rests on (NaN: no
    estimate yet). ``seat_drops``: checks of the magnet's hold the vehicle came down in
    (``control.seat_check``); ``leans_refused``: the pilot sent velocities once the vehicle
    did not fly its leans (``control.lean_follow``)."""

    seed: int
    estimator: str
    success: bool
    reason: str
    contact_offset_mm: float
    contact_speed_mps: float
    time_to_perch_s: float
    t_s: Array = field(repr=False)
    p_magnet_m: Array = field(repr=False)
    stage: NDArray[np.int64] = field(repr=False)
    phase: tuple[str, ...] = field(repr=False)
    tries: int = 0
    wind_direction_rad: float = 0.0
    contact: Contact | None = None
    senses: SensingDraw | None = None
    fault: Fault | None = None
    motor_stop_height_m: float = math.nan
    pilot_states: str = ""
    max_setpoint_gap_s: float = math.nan
    time_offset: OffsetReport = field(default_factory=lambda: NO_OFFSET)
    time_offset_end: OffsetReport = field(default_factory=lambda: NO_OFFSET)
    seated_offset_mm: float = math.nan
    stop_after_contact_s: float = math.nan
    seat_drops: int = 0
    leans_refused: bool = False


class Lean(NamedTuple):
    """An attitude setpoint as the commander holds it: roll and pitch (rad, as
    ``AttitudeHold``), the height its loop holds (world z of the vehicle's estimate, m), or
    instead a collective thrust as a fraction of the hover's (cflib's legacy setpoint)."""

    roll_rad: float
    pitch_rad: float
    z_m: float
    thrust_fraction: float | None = None


class HeldSetpoint:
    """The commander the simulated vehicle flies: it holds the last setpoint that reached it,
    and no setpoint at all is a hover. A stop cuts the motors (``stopped``). ``clock`` gives
    the simulation's time; while ``link_up`` says no, nothing the pilot sends arrives, and
    ``received_s`` (when the last one did) ages, for the vehicle's own watchdog. What is sent
    reaches the vehicle ``delay_s`` later (the radio uplink); ``deliver`` hands over what has
    arrived by now, ``next_arrival_s`` says when the next will. ``velocity_gain`` sets the
    vehicle's horizontal velocity gain (None: its own back) and says whether it could, as a
    parameter set over the link does. ``position_fix`` hands the vehicle's estimator an
    external position as it arrives (None: the vehicle's estimator takes none)."""

    def __init__(
        self,
        clock: Callable[[], float] = lambda: 0.0,
        link_up: Callable[[], bool] = lambda: True,
        delay_s: float = 0.0,
        velocity_gain: Callable[[float | None], bool] = lambda _gain: False,
        position_fix: Callable[[Array], None] | None = None,
    ) -> None:
        self.velocity_gain = velocity_gain
        self.position_fix = position_fix
        self._fixes: deque[tuple[float, Array]] = deque()  # on their way: (arrival, position)
        self.v_mps = np.zeros(3)
        self.yaw_rate_rad_s = 0.0
        # a full-state setpoint's position (world frame of the vehicle's estimate) and yaw;
        # None while the last setpoint is a velocity
        self.position_m: Array | None = None
        self.yaw_rad = 0.0
        # an attitude setpoint's roll, pitch (rad) and height (world z of the vehicle's
        # estimate, m); None while the last setpoint is not one
        self.lean: Lean | None = None
        self.clock = clock
        self.link_up = link_up
        self.delay_s = delay_s
        self.stopped = False
        self.received_s: float | None = None  # the vehicle's watchdog starts at the first
        self.sent_s: list[float] = []  # when the pilot sent each command
        # on their way: (arrival time, velocity, yaw rate, stop, full state's position and
        # yaw, attitude setpoint's roll, pitch and height)
        self._pending: deque[
            tuple[
                float,
                Array,
                float,
                bool,
                tuple[Array, float] | None,
                Lean | None,
            ]
        ] = deque()

    def _send(
        self,
        v_mps: Array,
        yaw_rate_rad_s: float,
        stop: bool,
        full_state: tuple[Array, float] | None = None,
        lean: Lean | None = None,
    ) -> None:
        now = self.clock()
        self.sent_s.append(now)
        if self.link_up():
            arrival_s = now + self.delay_s
            self._pending.append((arrival_s, v_mps, yaw_rate_rad_s, stop, full_state, lean))
            self.deliver()

    def deliver(self) -> None:
        """Take every setpoint that has arrived by now."""
        now = self.clock()
        while self._pending and self._pending[0][0] <= now + 1e-12:
            arrived_s, v_mps, yaw_rate, stop, full_state, lean = self._pending.popleft()
            self.received_s = arrived_s
            self.v_mps, self.yaw_rate_rad_s = v_mps, yaw_rate
            self.position_m, self.yaw_rad = full_state or (None, 0.0)
            self.lean = lean
            self.stopped = self.stopped or stop
        while self._fixes and self._fixes[0][0] <= now + 1e-12:
            _, p_m = self._fixes.popleft()
            if self.position_fix is not None:
                self.position_fix(p_m)

    def next_arrival_s(self) -> float | None:
        heads = [q[0][0] for q in (self._pending, self._fixes) if q]
        return min(heads) if heads else None

    def send_position_fix(self, p_world_m: tuple[float, float, float]) -> bool:
        """An external position for the vehicle's estimator, over the same uplink."""
        if self.position_fix is None:
            return False
        if self.link_up():
            self._fixes.append((self.clock() + self.delay_s, np.array(p_world_m, np.float64)))
            self.deliver()
        return True

    def send_velocity(self, v_world_mps: tuple[float, float, float], yaw_rate_rad_s: float) -> None:
        self._send(np.array(v_world_mps, np.float64), yaw_rate_rad_s, False)

    def send_full_state(
        self,
        p_world_m: tuple[float, float, float],
        v_world_mps: tuple[float, float, float],
        yaw_rad: float,
        yaw_rate_rad_s: float,
    ) -> None:
        """A full-state setpoint: the vehicle holds the position and yaw with its own loops."""
        full = (np.array(p_world_m, np.float64), float(yaw_rad))
        self._send(np.array(v_world_mps, np.float64), yaw_rate_rad_s, False, full)

    def send_attitude(
        self, roll_rad: float, pitch_rad: float, yaw_rate_rad_s: float, z_m: float
    ) -> None:
        """An attitude setpoint: the vehicle leans so and holds the height with its own loop."""
        lean = Lean(float(roll_rad), float(pitch_rad), float(z_m))
        self._send(np.zeros(3), yaw_rate_rad_s, False, None, lean)

    def send_level_thrust(self, hover_fraction: float) -> None:
        """Level, no yaw rate, and this fraction of the hover's thrust (cflib's legacy
        ``send_setpoint``): no height loop."""
        lean = Lean(0.0, 0.0, math.nan, float(hover_fraction))
        self._send(np.zeros(3), 0.0, False, None, lean)

    def send_stop(self) -> None:
        self._send(np.zeros(3), 0.0, True)

    def send_land(self) -> bool:
        """The simulated vehicle has no landing of its own: the pilot lands it."""
        return False

    def set_velocity_gain(self, gain_per_s: float) -> bool:
        return self.link_up() and self.velocity_gain(gain_per_s)

    def restore_velocity_gain(self) -> None:
        if self.link_up():
            self.velocity_gain(None)


def truth_estimate(
    T_camera_target: Array, camera: CameraModel, target: TargetSpec, t_s: float
) -> Estimate:
    """The controller's limit: the true pose, valid while a marker is in view."""
    in_view = markers_in_view(camera, target, T_camera_target)
    stage = stage_of({i for i, v in enumerate(in_view) if v})
    valid = stage > 0
    if not valid:
        return Estimate.none(t_s)
    t = T_camera_target[:3, 3]
    roll, pitch = tilt_rad(T_camera_target[:3, :3])
    return Estimate(
        t_s=t_s,
        valid=True,
        stage=stage,
        t_camera_target_m=(float(t[0]), float(t[1]), float(t[2])),
        yaw_rad=yaw_rad(T_camera_target[:3, :3]),
        roll_rad=roll,
        pitch_rad=pitch,
    )


def _estimator_for(setup: PerchSetup, camera: CameraModel) -> PerchingEstimator | None:
    """The run's estimator, given the calibration the user has (``camera``)."""
    if setup.estimator == "truth":
        return None
    if setup.estimator == "covariance":
        return PerchingEstimator(camera, setup.target, fusion="covariance")
    markers = {"paper": None, "outer": (0,), "inner": tuple(range(1, len(setup.target.markers)))}
    return PerchingEstimator(camera, setup.target, markers=markers[setup.estimator], fusion="paper")


def _plant_for(setup: PerchSetup, plant: Plant) -> Plant:
    """What makes the run's vehicle: ``plant``, or with one of the firmware's flight
    controllers this package's ``Quadrotor`` flown by it."""
    if setup.flight_controller == "model":
        return plant
    if plant is not Quadrotor.hovering:
        raise VehicleConfigError(
            f"the {setup.flight_controller} flight controller flies this package's Quadrotor, "
            "not another plant"
        )
    return partial(
        FirmwareQuadrotor.hovering_on_firmware, setup.flight_controller, setup.physics_hz
    )


def _draw_senses(
    setup: PerchSetup,
    rng: np.random.Generator,
    stamps_seq: np.random.SeedSequence,
    uplink_seq: np.random.SeedSequence,
) -> SensingDraw:
    """A run's realistic senses: drawn from ``rng``; the latency the user measured (its
    error from ``stamps_seq``) and the uplink's delay (from ``uplink_seq``) each from a
    generator of its own, so that the earlier draws stay as they were."""
    senses = SensingDraw.draw(setup.sensing, setup.camera, rng)
    measured = mean_glass_to_grab_s(
        senses.latency_s,
        setup.sensing.latency_jitter_s,
        setup.fps,
        setup.disturbances.latency_jitter,
    )
    error = float(np.random.default_rng(stamps_seq).uniform(-1.0, 1.0))
    uplink = np.random.default_rng(uplink_seq)
    return replace(
        senses,
        latency_configured_s=measured + error * setup.sensing.latency_error_s,
        uplink_delay_s=float(uplink.uniform(*setup.sensing.uplink_delay_s)),
    )


def _onboard_kalman(
    setup: PerchSetup, vehicle: Quadrotor, seed: np.random.SeedSequence
) -> CrazyflieKalman | None:
    """The firmware's Kalman filter flying ``vehicle`` (settled on it), where the setup asks
    for it; None: the model's estimate."""
    if setup.onboard_estimator != "crazyflie-kalman":
        return None
    kalman = CrazyflieKalman(
        load_firmware(),
        KalmanSenses(),
        setup.sensing.flow_deck,
        np.random.default_rng(seed),
        vehicle,
    )
    kalman.settle(vehicle)
    vehicle.estimator = kalman
    return kalman


def set_on_floor(vehicle: Quadrotor) -> bool:
    """Stand a vehicle whose feet met the floor on it, still; True if it came down softly,
    False if it fell (faster than ``FLOOR_CRASH_MPS`` or tilted over 30 degrees)."""
    hard = float(np.linalg.norm(vehicle.v_mps)) > FLOOR_CRASH_MPS or tilt_deg(vehicle) > 30.0
    p = vehicle.p_m
    vehicle.p_m = np.array([p[0], p[1], REST_Z_M])
    vehicle.v_mps = np.zeros(3)
    return not hard


def draw_start(setup: PerchSetup, world: np.random.Generator) -> tuple[Array, float]:
    """A run's start, hovering under the plate (world frame, m), and its heading (rad)."""
    below = float(world.uniform(*setup.start_below_m))
    lateral = setup.start_lateral_fraction * below
    start = np.array(
        [
            world.uniform(-lateral, lateral),
            world.uniform(-lateral, lateral),
            setup.plate_z_m - below,
        ]
    )
    return start, float(world.uniform(-math.pi, math.pi))


@dataclass
class MotorStop:
    """When and where a run's motors stopped, and what its end is judged on: the first
    contact's time, whether the motors stopped with the gear against the plate, the height
    above what the vehicle rests on (NaN until they stop), and where the gear sat when the
    perch was judged."""

    motors_stopped: bool = False
    motor_stop_height_m: float = math.nan
    floor_height_m: float = math.nan  # the body's height above its rest on the floor then
    stopped_at_s: float = math.nan
    stopped_at_plate: bool = False
    touched_at_s: float = math.nan
    seated_offset_mm: float = math.nan


class _Flight:
    """One run's world and vehicle, stepped frame by frame."""

    def __init__(
        self,
        setup: PerchSetup,
        seed: int,
        renderer: Renderer[TargetSpec],
        plant: Plant = Quadrotor.hovering,
    ) -> None:
        self.setup, self.seed = setup, seed
        # the senses draw from a third generator: ideal senses fly the worlds they always did;
        # the latency the user measured from a fourth (exact stamps fly what they always did)
        seeds = np.random.SeedSequence(seed).spawn(10)
        world_seq, camera_seq, senses_seq, stamps_seq, faults_seq, range_seq, flow_seq = seeds[:7]
        self.fault = Fault.draw(setup.faults, np.random.default_rng(faults_seq))
        self.range_rng = np.random.default_rng(range_seq)
        self._height_error = (0.0, 0.0)  # the fused height's error (m) and when it was drawn
        world = np.random.default_rng(world_seq)
        self.camera_rng = np.random.default_rng(camera_seq)
        self.senses_rng = np.random.default_rng(senses_seq)
        start, heading_rad = draw_start(setup, world)
        self.vehicle = _plant_for(setup, plant)(setup.vehicle, start, heading_rad, setup.onboard)
        self.vehicle.ceiling_z_m, self.vehicle.ceiling_half_size_m = (
            setup.plate_z_m if setup.ceiling_effect else None,
            setup.contact.plate_half_size_m,
        )
        self.wind_direction_rad = float(world.uniform(-math.pi, math.pi))
        self.wind = DrydenWind(
            setup.wind_level, 1.0 / setup.fps, world, self.wind_direction_rad, setup.plate_z_m
        )
        self.draw = VehicleDraw.draw(setup.disturbances, setup.duration_s, world)
        self.vehicle.attitude_bias = self.draw.attitude_bias
        self.vehicle.thrust_scale = self.draw.thrust_scale(0.0)
        self.vehicle.settle()
        self.kalman = _onboard_kalman(setup, self.vehicle, seeds[9])
        self._hover_in_the_wind(start)
        self.senses: SensingDraw | None = None
        self.T_body_camera = np.asarray(setup.controller.T_body_camera, np.float64)
        flow_noise = 0.0
        flow: FlowDeckError | None = None
        if not setup.sensing.is_ideal:
            self.senses = _draw_senses(setup, self.senses_rng, stamps_seq, seeds[7])
            self.T_body_camera = self.T_body_camera @ self.senses.T_true_believed
            flow_noise = setup.sensing.flow_noise_mps
            if setup.sensing.odometry == "flow-deck":
                flow = FlowDeckError(setup.sensing.flow_deck, np.random.default_rng(flow_seq))
        self.odometry = OdometryModel(setup.disturbances, start, world, flow_noise, flow)
        self.render = renderer
        self.estimator = _estimator_for(
            setup, self.senses.camera if self.senses is not None else setup.camera
        )
        self.commander = self._commander()
        self.resting = False  # on the floor, its weight on its feet
        self.stop = MotorStop()
        self.controller = PerchingController(setup.controller)
        self.now_s = 0.0
        self.sensed, self.accelerometer = self._sense_chain(seeds[8])
        self.sense(0.0)
        self.pilot = PerchingPilot(
            self.commander,
            self.attitude,
            controller=self.controller,
            settings=setup.pilot,
            height_m=self.height_m,
            odometry=self.motion,
            ages=None if self.sensed is None else self.sense_ages,
            report=log.debug,
            specific_force=self.specific_force,
            gyro=self.gyro,
        )
        magnet = setup.controller.p_body_magnet_m
        holds = setup.contact_mode == "hold"
        self.plate = PlateContact(setup.plate_z_m, magnet, setup.contact, goes_on=holds)
        # the plate's forces on the vehicle (the flight goes on through the contact)
        self.forces = self._plate_forces() if holds else None
        self._block = (0.0, 0)  # the block being flown: its start, and the steps flown of it
        # frames on their way to the estimator: (arrival frame, stamp, true capture time,
        # image or pose)
        self.pipeline: deque[tuple[int, float, float, Array | NDArray[np.uint8] | None]] = deque()
        self._last_arrival = 0
        # each frame the pilot got: its stamp, and how far its true capture time is from it (s)
        self.stamp_errors: list[tuple[float, float]] = []
        self.offset_at: OffsetReport | None = None  # the estimate after OFFSET_AT_S

    def _sense_chain(
        self, accel_seq: np.random.SeedSequence
    ) -> tuple[SensedState | None, Accelerometer | None]:
        """The flight controller's samples on their way to the pilot, and its accelerometer
        (None, None: ideal senses, the pilot reads the vehicle's state as it is)."""
        if self.senses is None:
            return None, None
        sensing = self.setup.sensing
        return (
            SensedState(self.senses.attitude_delay_s, self.senses.odometry_delay_s),
            Accelerometer(
                sensing.accel_noise_mps2, sensing.accel_bias_mps2, np.random.default_rng(accel_seq)
            ),
        )

    def _plate_forces(self) -> PlateForces:
        """The plate's face, friction and magnet, acting on the vehicle."""
        s = self.setup
        if not self.vehicle.takes_plate_forces:
            raise VehicleConfigError(
                f"{type(self.vehicle).__name__} takes no plate forces: fly it with "
                "contact_mode='first-touch'"
            )
        forces = PlateForces(
            s.plate_z_m, s.controller.p_body_magnet_m, s.contact, s.magnet, s.surface
        )
        self.vehicle.plate = forces
        return forces

    def _commander(self) -> HeldSetpoint:
        """The vehicle's end of the link: setpoints (and position fixes, where its Kalman
        filter takes them) after the uplink's delay, none while the link is lost."""
        return HeldSetpoint(
            lambda: self.now_s,
            lambda: not self.faulty("link-loss", self.now_s),
            0.0 if self.senses is None else self.senses.uplink_delay_s,
            self.vehicle.set_velocity_gain,
            None if self.kalman is None else self._position_fix,
        )

    def _position_fix(self, p_m: Array) -> None:
        """An external position reaches the vehicle's Kalman filter."""
        assert self.kalman is not None
        self.kalman.external_position(p_m, self.setup.controller.position_fixes.std_m)

    def faulty(self, kind: str, t_s: float) -> bool:
        """The run's fault is ``kind`` and is on at ``t_s``."""
        return self.fault is not None and self.fault.kind == kind and self.fault.active(t_s)

    def _through(self, sense: str) -> float:
        """Up to when the flight controller's ``sense`` samples have got through (a stalled
        stream: its stall's start)."""
        if self.fault is not None and self.faulty(f"{sense}-stall", self.now_s):
            return self.fault.start_s
        return self.now_s

    def attitude(self) -> Array:
        """The attitude the pilot has now: the flight controller's estimate, as it arrives."""
        if self.sensed is None:
            return self.vehicle.R_estimate
        return self.sensed.attitude(self._through("attitude"))

    def motion(self) -> tuple[Array, Array]:
        """The odometry the pilot has now (position, velocity), as it arrives."""
        if self.sensed is None:
            return self._odometry_now()
        return self.sensed.odometry(self._through("odometry"))

    def _odometry_now(self) -> tuple[Array, Array]:
        """The flight controller's position and velocity estimate now: its Kalman filter's,
        or the odometry model's."""
        if self.kalman is not None:
            return self.kalman.position_m, self.kalman.velocity_mps
        return self.odometry.p_m, self.odometry.v_mps

    def gyro(self) -> GyroReading | None:
        """The firmware's gyro, logged with its attitude, integrated as it arrives (None with
        ideal senses or the model's estimator: its attitude knows its tilt)."""
        if self.sensed is None:
            return None
        return self.sensed.gyro_reading(self._through("attitude"))

    def specific_force(self) -> Array | None:
        """The accelerometer's sample the pilot has now (body frame), as it arrives."""
        if self.sensed is None:
            return self.vehicle.specific_force_body_mps2
        return self.sensed.specific_force(self._through("odometry"))

    def height_m(self) -> float:
        """The height the pilot has. With faults (runs that go on to a landing): above the
        floor (0 standing on it), as the flight controller's estimate gives it with a range
        sensor under the vehicle (exact with ideal senses): a Flow deck's VL53L1x reads at
        40 Hz with noise of 5 mm plus 1 % of the range, which the estimate fuses with the
        accelerometer; its error is taken as the readings' low-passed over
        ``FUSED_HEIGHT_TAU_S`` (a quarter of a reading's spread, correlated over that time).
        Otherwise the odometry's, as the campaigns measured before faults were flown."""
        if not self.setup.to_motor_stop:
            return float(self.motion()[0][2])
        if self.kalman is not None:
            return float(self.kalman.position[2]) - REST_Z_M
        h = float(self.vehicle.p_m[2]) - REST_Z_M
        if self.sensed is None:
            return h
        error, drawn_s = self._height_error
        keep = math.exp(-max(0.0, self.now_s - drawn_s) / FUSED_HEIGHT_TAU_S)
        sigma = FUSED_HEIGHT_SHARE * (0.005 + 0.01 * abs(h))
        error = keep * error + math.sqrt(1.0 - keep * keep) * sigma * self.range_rng.normal()
        self._height_error = (error, self.now_s)
        return h + error

    def sense_ages(self) -> SenseAges:
        """How old the attitude and odometry the pilot has now are (realistic senses)."""
        assert self.sensed is not None
        attitude_at, odometry_at = self._through("attitude"), self._through("odometry")
        attitude_s = self.sensed.ages(attitude_at)[0] + self.now_s - attitude_at
        odometry_s = self.sensed.ages(odometry_at)[1] + self.now_s - odometry_at
        return SenseAges(attitude_s, odometry_s, odometry_s)

    def sense(self, t_s: float) -> None:
        """The flight controller makes a sample of its state now (realistic senses only)."""
        if self.sensed is None:
            return
        R = self.vehicle.R_estimate
        if self.kalman is None:  # the model's estimate has no noise of its own
            R = noisy_attitude(R, self.setup.sensing.attitude_noise_deg, self.senses_rng)
        assert self.accelerometer is not None
        f_body = self.accelerometer.read(self.vehicle.specific_force_body_mps2)
        gyro_dps = None if self.kalman is None else self.kalman.gyro_dps
        self.sensed.record(t_s, R, *self._odometry_now(), f_body, gyro_dps)

    def frames_late(self) -> int:
        """How many frame periods after its capture this frame reaches the pilot: the
        latency (with its jitter) to the next frame's tick, at least one."""
        s = self.setup
        if self.senses is None:
            return s.latency_frames
        jitter = abs(float(self.senses_rng.normal(0.0, s.sensing.latency_jitter_s)))
        return max(1, math.ceil((self.senses.latency_s + jitter) * s.fps - 1e-9))

    def capture(self, k: int, t_s: float) -> None:
        """The camera captures frame ``k`` now; it arrives ``frames_late`` (sometimes one
        more) frames later, never before the frame captured before it."""
        s = self.setup
        if self.offset_at is None and t_s >= OFFSET_AT_S:
            self.offset_at = self.offset_report()
        rng = self.camera_rng
        T_world_camera = make_transform(self.vehicle.R_world_body, self.vehicle.p_m)
        T_camera_target = invert_transform(T_world_camera @ self.T_body_camera) @ s.T_world_target
        dropped = rng.random() < s.drop_probability or self.draw.in_burst(t_s)
        late = rng.random() < s.disturbances.latency_jitter
        arrival = max(self._last_arrival, k + self.frames_late() + int(late))
        self._last_arrival = arrival
        payload: Array | NDArray[np.uint8] | None
        if dropped:
            payload = None
        elif self.estimator is None:
            payload = T_camera_target
        else:
            shown = T_camera_target
            if self.senses is not None:  # a print s times the size at d looks as one at d / s
                shown = T_camera_target.copy()
                shown[:3, 3] /= self.senses.target_scale
            payload = self.render.render(shown, s.quality, rng)
        if self.senses is None:
            stamp = t_s
        elif s.stamps == "live":  # as a live source stamps it: its grab, less the latency set
            grabbed = _step_of(arrival, s.fps, s.physics_hz) / s.physics_hz
            stamp = grabbed - self.senses.latency_configured_s
        else:
            stamp = t_s + self.senses.clock_offset_s
        self.pipeline.append((arrival, stamp, t_s, payload))

    def offset_report(self) -> OffsetReport:
        """The controller's time-offset estimate now, with the truth over its frames."""
        e = self.controller.time_offset
        if e is None:
            return NO_OFFSET
        truth = [err for stamp, err in self.stamp_errors if e.from_s <= stamp <= e.to_s]
        return OffsetReport(e.offset_s, e.sigma_s, float(np.mean(truth)) if truth else math.nan)

    def arrived(self, k: int) -> Estimate | None:
        """Every frame that has reached the estimator by frame ``k``, in order; the newest
        estimate (None when no frame arrived)."""
        s = self.setup
        estimate = None
        true_s = math.nan
        while self.pipeline and self.pipeline[0][0] <= k:
            _, stamp, captured_s, payload = self.pipeline.popleft()
            if payload is None:
                continue
            true_s = captured_s
            if self.estimator is None:
                estimate = truth_estimate(
                    np.asarray(payload, np.float64), s.camera, s.target, stamp
                )
            else:
                estimate = self.estimator.update(np.asarray(payload, np.uint8), stamp)
        if estimate is not None:
            self.stamp_errors.append((estimate.t_s, true_s - estimate.t_s))
        return estimate

    def _hover_in_the_wind(self, start_m: Array) -> None:
        """Hold the start ``hover_s`` on the vehicle's own loops and estimator (a position
        hold, as a vehicle flown to its start waits there) in the wind as it blows when the run
        starts, then put the vehicle back at ``start_m`` with its lean, its motion and its
        loops' and estimator's states as the hover left them: the pilot takes over a vehicle
        that has flown in that wind, not one the whole wind strikes at the run's start."""
        v, s = self.vehicle, self.setup
        steps = round(s.hover_s * s.physics_hz)
        if steps == 0 or s.wind_level.calm:
            return
        v.wind_mps = self.wind.now()
        dt_s = 1.0 / s.physics_hz
        start, yaw_rad = vec3(start_m), v.yaw_rad
        for _ in range(steps):  # the model's loops hold it on the true position, step by step
            v.hold = PositionHold(start, yaw_rad, vec3(v.p_m))
            v.fly(dt_s, 1, np.zeros(3), 0.0, v.v_mps)
        v.hold = None
        v.p_m = np.array(start_m, np.float64)

    def fly(self, t_s: float, steps: int) -> int | None:
        """The vehicle through ``steps`` physics steps from ``t_s`` on the setpoint it holds,
        taking each setpoint on its way at the step it arrives; the odometry follows. The
        contact step (``plate.contact`` says what touched) or None."""
        dt_s = 1.0 / self.setup.physics_hz
        c = self.commander
        event_s, done = self.now_s, 0
        try:
            while done < steps:
                self.now_s = t_s + done * dt_s
                c.deliver()
                block = steps - done
                arrival = c.next_arrival_s()
                if arrival is not None:
                    block = min(block, max(1, math.ceil((arrival - self.now_s) / dt_s - 1e-9)))
                contact = self._fly_block(self.now_s, block)
                if contact is not None:
                    return done + contact
                done += block
            return None
        finally:
            self.now_s = event_s

    def _fly_block(self, t_s: float, steps: int) -> int | None:
        """``fly`` on one setpoint."""
        s = self.setup
        v = self.vehicle
        dt_s = 1.0 / s.physics_hz
        c = self.commander
        silent_s = 0.0 if c.received_s is None else t_s - c.received_s
        stops = c.stopped or silent_s >= MOTORS_OFF_AFTER_S
        if (s.to_motor_stop or self.forces is not None) and not self.stop.motors_stopped and stops:
            self.stop.motors_stopped = True  # the pilot's stop, or the vehicle's own watchdog
            self.stop.stopped_at_s = t_s
            self.stop.stopped_at_plate = self.forces is not None and self.forces.at_plate(
                v, AT_PLATE_M
            )
            rests = self.resting or self.stop.stopped_at_plate
            self.stop.floor_height_m = float(v.p_m[2]) - REST_Z_M
            self.stop.motor_stop_height_m = 0.0 if rests else self.stop.floor_height_m
            if self.kalman is not None:
                self.kalman.flying = False
        v_sp = c.v_mps if silent_s < LEVEL_AFTER_S else np.zeros(3)
        # a full state to hold, from the vehicle's own estimate (a silent link levels the
        # vehicle: no more holding)
        hold: Hold | None = None
        if c.position_m is not None and silent_s < LEVEL_AFTER_S:
            p_est = vec3(self._odometry_now()[0])
            hold = PositionHold(vec3(c.position_m), c.yaw_rad, p_est, vec3(c.v_mps))
            v_sp = c.position_m - np.array(p_est)
        elif c.lean is not None and silent_s < LEVEL_AFTER_S:
            p_est = vec3(self._odometry_now()[0])
            roll, pitch, z_m, thrust = c.lean
            hold = AttitudeHold(roll, pitch, c.yaw_rate_rad_s, z_m, p_est, thrust)
            # a thrust under the hover's (a check of the magnet's hold) asks down
            v_sp = np.array([0.0, 0.0, -1.0 if thrust is not None else z_m - p_est[2]])
        if self.resting and (self.stop.motors_stopped or v_sp[2] <= 0.0):
            self._follow(dt_s * steps)  # on the floor, still
            if self.kalman is not None:
                self.kalman.advance(dt_s * steps, v)
            return None
        self.resting = False
        v.thrust_scale = (0.0,) * 4 if self.stop.motors_stopped else self.draw.thrust_scale(t_s)
        v.hold = hold
        self._block = (t_s, 0)
        contact = v.fly(
            dt_s,
            steps,
            v_sp,
            c.yaw_rate_rad_s if silent_s < LEVEL_AFTER_S else 0.0,
            self.odometry.v_mps,
            touched=self._touched,
        )
        self._follow(dt_s * (steps if contact is None else contact + 1))
        return contact

    def _follow(self, dt_s: float) -> None:
        """The odometry model follows the vehicle through ``dt_s`` (a Kalman filter in the
        loop follows it step by step in ``Quadrotor.fly``)."""
        if self.kalman is not None:
            return
        v = self.vehicle
        self.odometry.update(v.p_m, v.v_mps, dt_s, v.R_world_body, v.omega_rad_s)

    def _touched(self, vehicle: Quadrotor) -> bool:
        """The vehicle touched the plate (at all with ``first-touch`` contacts; with a rotor
        where the flight goes on through the contact), or (with faults, whose runs go on to a
        landing) its feet met the floor."""
        start_s, flown = self._block
        self._block = (start_s, flown + 1)
        first = self.plate.contact is None
        if self.plate(vehicle):
            return True
        if first and self.plate.contact is not None:
            self.stop.touched_at_s = start_s + (flown + 1) / self.setup.physics_hz
        return self.setup.to_motor_stop and vehicle.p_m[2] <= REST_Z_M and vehicle.v_mps[2] < 0.0

    def ended(self, contact_step: int | None, t_s: float, now_s: float) -> Outcome | None:
        """How the run ended, after the block flown from ``t_s`` to ``now_s`` (in which
        ``fly`` stopped at ``contact_step``, or None); None while it goes on."""
        touched = self._contact_outcome(contact_step, t_s)
        if touched is not None:
            return touched
        if self.stop.stopped_at_plate:
            return self._hold_outcome(now_s)
        if (contact_step is not None and not self.on_floor()) or self.crashed():
            return _no_perch("crash")
        landing = self.pilot.state in (PilotState.LANDING, PilotState.LANDED)
        goes_on = self.setup.to_motor_stop
        stops = goes_on or self.forces is not None
        if (landing and not goes_on) or (stops and self.stop.motors_stopped):
            reason = "gave-up" if self.controller.phase == Phase.GIVE_UP else "lost"
            if self.stop.motor_stop_height_m > FALL_M:  # stopped in the air: it falls
                reason = "crash"
            return _no_perch(reason)
        return None

    def _contact_outcome(self, contact_step: int | None, t_s: float) -> Outcome | None:
        """A contact that ends the run: any first touch scored by the contact rules (with
        ``first-touch``), or a rotor striking the plate."""
        touch = self.plate.contact
        if touch is None:
            return None
        dt_s = 1.0 / self.setup.physics_hz
        if self.forces is None and contact_step is not None:
            reason = touch.verdict(self.setup.contact)
            if reason == "perched" and self.setup.to_motor_stop:
                self.stop.motor_stop_height_m = 0.0  # the magnet holds it; the pilot stops them
            t_contact = t_s + (contact_step + 1) * dt_s
            return (reason == "perched", reason, touch.offset_mm, touch.v_mps[2], t_contact, touch)
        if self.plate.struck is not None:
            t_strike = t_s + (contact_step or 0) * dt_s
            return (False, "rotor-strike", touch.offset_mm, touch.v_mps[2], t_strike, touch)
        return None

    def _hold_outcome(self, now_s: float) -> Outcome | None:
        """The motors stopped against the plate: the perch judged ``HOLD_S`` later, or as
        soon as the gear has fallen ``FELL_M`` from it (None until then)."""
        assert self.forces is not None
        touch = self.plate.contact
        assert touch is not None
        gap_m = self.forces.gap_m(self.vehicle)
        if gap_m <= FELL_M and now_s - self.stop.stopped_at_s < HOLD_S:
            return None
        reason = self.hold_verdict(gap_m)
        at = self.stop.stopped_at_s
        return (reason == "perched", reason, touch.offset_mm, touch.v_mps[2], at, touch)

    def after_the_end(self, end_s: float) -> Outcome:
        """The end of a run that lasted its whole duration. Motors stopped against the plate
        in time are judged as ever, ``HOLD_S`` after the stop: the vehicle goes on, unpowered,
        past the end until the magnet's hold is seen (or the gear falls)."""
        hz = self.setup.physics_hz
        t_s = end_s
        while self.stop.stopped_at_plate and t_s < self.stop.stopped_at_s + HOLD_S + 1.0 / hz:
            steps = max(1, math.ceil((self.stop.stopped_at_s + HOLD_S - t_s) * hz - 1e-9))
            self.now_s = t_s
            contact = self.fly(t_s, steps)
            flown = steps if contact is None else contact + 1
            outcome = self.ended(contact, t_s, t_s + flown / hz)
            if outcome is not None:
                return outcome
            t_s += flown / hz
        return self.timed_out()

    def timed_out(self) -> Outcome:
        """The end of a run that lasted its whole duration."""
        touch = self.plate.contact
        if self.forces is not None and touch is not None and touch.part == MAGNET:
            # against the plate with the motors running to the end
            return (False, "not-stopped", touch.offset_mm, touch.v_mps[2], math.nan, touch)
        return _no_perch("timeout")

    def hold_verdict(self, gap_m: float) -> str:
        """How a vehicle whose motors stopped against the plate ended: ``perched`` (the gear
        seated and the vehicle still, held by the magnet), ``fell`` (the gear ``FELL_M``
        below the plate), or ``not-seated`` (held, but not flat or still)."""
        assert self.forces is not None
        v = self.vehicle
        x, y, _ = v.point_in_world(self.setup.controller.p_body_magnet_m)
        self.stop.seated_offset_mm = 1000.0 * math.hypot(x, y)
        if gap_m > FELL_M:  # nothing held it: its motors stopped that high above the floor
            self.stop.motor_stop_height_m = self.stop.floor_height_m
            return "fell"
        still = float(np.linalg.norm(v.v_mps)) < STILL_MPS
        return "perched" if self.forces.seated(v) and still else "not-seated"

    def on_floor(self) -> bool:
        """The vehicle's feet met the floor: it rests there (True), or it fell on it (False:
        faster than ``FLOOR_CRASH_MPS`` or tilted over 30 degrees)."""
        self.resting = set_on_floor(self.vehicle)
        return self.resting

    def crashed(self) -> bool:
        v = self.vehicle
        return bool(v.p_m[2] < 0.02 or tilt_deg(v) > MAX_TILT_DEG or not np.isfinite(v.p_m).all())


# a run's end: success, reason, contact offset (mm), contact speed (m/s), time (s), the contact
Outcome = tuple[bool, str, float, float, float, Contact | None]


def _no_perch(reason: str) -> Outcome:
    """A run that ended without a contact to tell of."""
    return (False, reason, math.nan, math.nan, math.nan, None)


def _step_of(n: int, rate_hz: float, physics_hz: float) -> int:
    """The first physics step at or after the ``n``-th tick of a ``rate_hz`` clock."""
    return int(math.ceil(n * physics_hz / rate_hz - 1e-9))


def event_steps(
    setup: PerchSetup, odometry_hz: float | None = None
) -> list[tuple[int, int | None]]:
    """The physics steps at which something happens, in order: (step, frame index) for a
    camera frame, (step, None) for an odometry sample between frames (at ``odometry_hz``,
    default the setup's)."""
    hz = setup.physics_hz
    rate = setup.odometry_hz if odometry_hz is None else odometry_hz
    frames = {_step_of(k, setup.fps, hz): k for k in range(int(setup.duration_s * setup.fps) + 1)}
    ticks: set[int] = set()
    if rate > 0:
        count = int(setup.duration_s * rate) + 1
        ticks = {_step_of(j, rate, hz) for j in range(count)}
    steps = sorted(i for i in frames.keys() | ticks if i < setup.physics_steps)
    return [(i, frames.get(i)) for i in steps]


class _Trace:
    """A run's rows, one per camera frame (and one at a contact between frames): time, the
    magnet's position, the estimate's stage and the pilot's phase or state."""

    def __init__(self) -> None:
        self.ts: list[float] = []
        self.magnets: list[Array] = []
        self.stages: list[int] = []
        self.phases: list[str] = []

    def frame(self, t_s: float, stage: int, phase: str) -> None:
        self.ts.append(t_s)
        self.stages.append(stage)
        self.phases.append(phase)

    def result(
        self,
        flight: _Flight,
        outcome: tuple[bool, str, float, float, float],
        contact: Contact | None,
    ) -> PerchResult:
        """The run's result: ``outcome`` is (success, reason, offset, speed, time)."""
        success, reason, offset, speed, t = outcome
        pilot = flight.pilot
        states = ";".join(f"{after}@{at:.2f}" for at, _, after in pilot.transitions)
        return PerchResult(
            flight.seed,
            flight.setup.estimator,
            success,
            reason,
            offset,
            speed,
            t,
            np.array(self.ts),
            np.array(self.magnets).reshape(-1, 3),
            np.array(self.stages, np.int64),
            tuple(self.phases),
            flight.controller.tries,
            flight.wind_direction_rad,
            contact,
            flight.senses,
            flight.fault,
            flight.stop.motor_stop_height_m,
            states,
            _max_gap_s(flight.commander.sent_s, self.ts[-1] if self.ts else 0.0, pilot.flying),
            flight.offset_at or NO_OFFSET,
            flight.offset_report(),
            flight.stop.seated_offset_mm,
            flight.stop.stopped_at_s - flight.stop.touched_at_s,
            pilot.seat_drops,
            pilot.leans_refused,
        )


def _max_gap_s(sent_s: list[float], end_s: float, still_flying: bool) -> float:
    """The longest time between two of the pilot's commands (and from the last one to
    ``end_s`` if the pilot still flies the vehicle then); NaN before the first."""
    if not sent_s:
        return math.nan
    times = [*sent_s, end_s] if still_flying else sent_s
    return float(np.max(np.diff(times))) if len(times) > 1 else 0.0


def run_perch(
    setup: PerchSetup,
    seed: int,
    renderer: Renderer[TargetSpec] | None = None,
    plant: Plant = Quadrotor.hovering,
) -> PerchResult:
    """One perching run from a random start drawn with ``seed``. ``plant`` makes the vehicle
    (parameters, start, heading, onboard gains): this package's ``Quadrotor`` by default,
    ``perchpose.sim.rotorpy_plant`` for RotorPy's."""
    flight = _Flight(setup, seed, renderer or setup.renderer(), plant)
    p_magnet_body = np.asarray(setup.controller.p_body_magnet_m, np.float64)
    trace = _Trace()

    def result(
        success: bool,
        reason: str,
        offset: float,
        speed: float,
        t: float,
        contact: Contact | None = None,
    ) -> PerchResult:
        return trace.result(flight, (success, reason, offset, speed, t), contact)

    senses = flight.senses
    events = event_steps(setup, senses.odometry_hz if senses is not None else None)
    dt_s = 1.0 / setup.physics_hz
    for n, (i, k) in enumerate(events):
        t = i * dt_s
        flight.now_s = t
        if k is not None and flight.faulty("camera-stall", t):  # no frame reaches the pilot
            flight.vehicle.wind_mps = flight.wind.step()
            flight.pilot.tick(t)
            trace.frame(t, 0, flight.pilot.state)
        elif k is None:  # an odometry sample between frames
            flight.pilot.tick(t)
        else:
            flight.vehicle.wind_mps = flight.wind.step()
            flight.capture(k, t)
            estimate = flight.arrived(k)
            step = flight.pilot.update(estimate, t)
            trace.frame(t, estimate.stage if estimate is not None else 0, step.phase or step.state)
        steps = (events[n + 1][0] if n + 1 < len(events) else setup.physics_steps) - i
        contact = flight.fly(t, steps)
        flight.sense((i + steps) * dt_s)
        if k is not None or contact is not None:
            magnet = np.array(flight.vehicle.point_in_world(tuple(p_magnet_body)))
            if k is None:  # contact between frames: its row
                trace.frame(t, 0, flight.controller.phase)
            trace.magnets.append(magnet)
        outcome = flight.ended(contact, t, (i + steps) * dt_s)
        if outcome is not None:
            return result(*outcome)
    return result(*flight.after_the_end(setup.physics_steps * dt_s))
