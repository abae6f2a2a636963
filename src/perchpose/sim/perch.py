"""Closed-loop perching in simulation: the vehicle, the camera in the loop, the estimator and
the perching pilot that also flies the Crazyflie; only the scoring reads the true pose."""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.control import ControllerSettings, PerchingController, PerchingPilot, PilotSettings
from perchpose.estimator import PerchingEstimator
from perchpose.fusion import stage_of
from perchpose.geometry import invert_transform, make_transform, rot_z, yaw_rad
from perchpose.sim.quadrotor import OnboardGains, Quadrotor, QuadrotorParams, VehicleConfigError
from perchpose.sim.render import ImageQuality, Renderer
from perchpose.sim.scenarios import markers_in_view
from perchpose.target import TargetSpec
from perchpose.values import Estimate

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

ESTIMATORS = ("paper", "outer", "inner", "covariance", "truth")
# standard deviation of the gust force, newtons (the vehicle weighs 0.38 N)
WIND_LEVELS = {"none": 0.0, "light": 0.004, "moderate": 0.008, "strong": 0.015}
CONTACT_RADIUS_MM = 12.5  # the paper's 25 mm magnet
MAX_CONTACT_SPEED_MPS = 0.3
R_WORLD_TARGET = np.diag([1.0, -1.0, -1.0])  # printed face down, x along world x


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
    duration_s: float = 20.0
    wind: str = "none"
    ceiling_effect: bool = True
    velocity_noise_mps: float = 0.01
    supersample: int = 1
    quality: ImageQuality = field(default_factory=ImageQuality)

    def __post_init__(self) -> None:
        if self.estimator not in ESTIMATORS:
            raise VehicleConfigError(
                f"unknown estimator {self.estimator!r} (choose {', '.join(ESTIMATORS)})"
            )
        if self.wind not in WIND_LEVELS:
            raise VehicleConfigError(
                f"unknown wind level {self.wind!r} (choose {', '.join(WIND_LEVELS)})"
            )
        low, high = self.start_below_m
        if not 0 < low <= high:
            raise VehicleConfigError("start_below_m must be 0 < low <= high")
        if not (self.fps > 0 and self.physics_hz >= self.fps and self.duration_s > 0):
            raise VehicleConfigError("need fps > 0, physics_hz >= fps and duration_s > 0")
        if abs(self.controller.camera_period_s - 1.0 / self.fps) > 1e-9:
            raise VehicleConfigError("the controller's camera_period_s must be 1 / fps")
        self.check_start_box()

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
    """One run. ``reason``: perched, off-centre, too-fast, timeout."""

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


class HeldSetpoint:
    """The commander the simulated vehicle flies: it holds the last setpoint the pilot sent
    (cflib's units: m/s and deg/s), and a stop or no setpoint at all is a hover."""

    def __init__(self) -> None:
        self.v_mps = np.zeros(3)
        self.yaw_rate_rad_s = 0.0

    def send_velocity_world_setpoint(self, vx: float, vy: float, vz: float, yawrate: float) -> None:
        self.v_mps = np.array([vx, vy, vz])
        self.yaw_rate_rad_s = math.radians(yawrate)

    def send_stop_setpoint(self) -> None:
        self.v_mps = np.zeros(3)
        self.yaw_rate_rad_s = 0.0

    def send_notify_setpoint_stop(self, remain_valid_milliseconds: int = 0) -> None:
        """Nothing to hand back in a simulation."""


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
    return Estimate(
        t_s=t_s,
        valid=True,
        stage=stage,
        t_camera_target_m=(float(t[0]), float(t[1]), float(t[2])),
        yaw_rad=yaw_rad(T_camera_target[:3, :3]),
    )


def _estimator_for(setup: PerchSetup) -> PerchingEstimator | None:
    if setup.estimator == "truth":
        return None
    if setup.estimator == "covariance":
        return PerchingEstimator(setup.camera, setup.target, fusion="covariance")
    markers = {"paper": None, "outer": (0,), "inner": tuple(range(1, len(setup.target.markers)))}
    return PerchingEstimator(
        setup.camera, setup.target, markers=markers[setup.estimator], fusion="paper"
    )


def run_perch(
    setup: PerchSetup, seed: int, renderer: Renderer[TargetSpec] | None = None
) -> PerchResult:
    """One perching run from a random start drawn with ``seed``."""
    rng = np.random.default_rng(seed)
    below = float(rng.uniform(*setup.start_below_m))
    lateral = setup.start_lateral_fraction * below
    start = np.array(
        [rng.uniform(-lateral, lateral), rng.uniform(-lateral, lateral), setup.plate_z_m - below]
    )
    vehicle = Quadrotor.hovering(
        setup.vehicle, start, float(rng.uniform(-math.pi, math.pi)), setup.onboard
    )
    vehicle.ceiling_z_m = setup.plate_z_m if setup.ceiling_effect else None
    render = renderer or setup.renderer()
    estimator = _estimator_for(setup)
    commander = HeldSetpoint()
    pilot = PerchingPilot(
        commander,
        lambda: vehicle.R_world_body,
        controller=PerchingController(setup.controller),
        settings=setup.pilot,
        height_m=lambda: float(vehicle.p_m[2]),
        report=log.debug,
    )
    T_world_target = setup.T_world_target
    mx, my, mz = (float(c) for c in setup.controller.p_body_magnet_m)
    p_magnet_body = (mx, my, mz)
    sigma_wind = WIND_LEVELS[setup.wind]
    gust = np.zeros(3)
    dt = 1.0 / setup.physics_hz
    steps_per_frame = max(1, int(round(setup.physics_hz / setup.fps)))
    pipeline: deque[tuple[float, Array | NDArray[np.uint8] | None]] = deque()
    phase = "waiting"
    ts, magnets, stages, phases = [], [], [], []
    n_frames = int(round(setup.duration_s * setup.fps))
    for k in range(n_frames):
        t = k / setup.fps
        # the camera captures now; the frame reaches the estimator latency_frames later
        T_camera_target = (
            invert_transform(setup.T_world_camera(vehicle.p_m, vehicle.R_world_body))
            @ T_world_target
        )
        dropped = rng.random() < setup.drop_probability
        if dropped:
            pipeline.append((t, None))
        elif estimator is None:
            pipeline.append((t, T_camera_target))
        else:
            pipeline.append((t, render.render(T_camera_target, setup.quality, rng)))
        stage = 0
        if len(pipeline) > setup.latency_frames:
            t_capture, payload = pipeline.popleft()
            if payload is not None:
                if estimator is None:
                    estimate = truth_estimate(
                        np.asarray(payload, np.float64), setup.camera, setup.target, t_capture
                    )
                else:
                    estimate = estimator.update(np.asarray(payload, np.uint8), t_capture)
                stage = estimate.stage
                step = pilot.update(estimate, t)
                phase = step.phase or step.state
        v_estimate = vehicle.v_mps + rng.normal(0.0, setup.velocity_noise_mps, 3)
        forces = None
        if sigma_wind > 0:
            forces = np.empty((steps_per_frame, 3))
            for i in range(steps_per_frame):
                gust += -gust * dt + sigma_wind * math.sqrt(2.0 * dt) * rng.normal(size=3)
                forces[i] = gust
        contact = vehicle.fly(
            dt,
            steps_per_frame,
            commander.v_mps,
            commander.yaw_rate_rad_s,
            v_estimate,
            forces,
            stop_z_m=setup.plate_z_m,
            p_body_point_m=np.array(p_magnet_body),
        )
        if contact is not None:
            magnet = np.array(vehicle.point_in_world(p_magnet_body))
            offset_mm = float(np.hypot(magnet[0], magnet[1]) * 1000.0)
            speed = float(vehicle.v_mps[2])
            ok_offset = offset_mm <= CONTACT_RADIUS_MM
            ok_speed = speed < MAX_CONTACT_SPEED_MPS
            reason = (
                "perched"
                if ok_offset and ok_speed
                else ("off-centre" if not ok_offset else "too-fast")
            )
            ts.append(t)
            magnets.append(magnet)
            stages.append(stage)
            phases.append(phase)
            return PerchResult(
                seed,
                setup.estimator,
                ok_offset and ok_speed,
                reason,
                offset_mm,
                speed,
                t,
                np.array(ts),
                np.array(magnets),
                np.array(stages, np.int64),
                tuple(phases),
            )
        ts.append(t)
        magnets.append(np.array(vehicle.point_in_world(p_magnet_body)))
        stages.append(stage)
        phases.append(phase)
    return PerchResult(
        seed,
        setup.estimator,
        False,
        "timeout",
        math.nan,
        math.nan,
        math.nan,
        np.array(ts),
        np.array(magnets),
        np.array(stages, np.int64),
        tuple(phases),
    )
