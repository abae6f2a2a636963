"""The perching position controller: from the target's estimated pose to velocity setpoints.

It is the same controller the simulation and the vehicle links use. Inputs: an ``Estimate`` (the
target in the camera frame), the mounting (``T_body_camera`` and the magnet's position on the
body) and the vehicle's own attitude ``R_world_body`` (world z up). Output: a world-frame
velocity setpoint and a yaw rate, as cflib's ``send_velocity_world_setpoint`` and MAVLink's
velocity setpoints take them.

Phases: ``search`` (no target yet: hold), ``align`` (centre the magnet under the target and turn
to its heading at constant height), ``climb`` (rise while keeping alignment, slowing near the
plate), ``commit`` (the last centimetres at a constant gentle speed), ``lost`` (target lost:
hold, then descend to re-acquire).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

from perchpose.errors import PerchposeError, require_positive
from perchpose.estimator import Estimate
from perchpose.geometry import check_transform, make_transform, wrap_angle_rad

Array = NDArray[np.float64]


class ControllerConfigError(PerchposeError):
    """Controller settings that cannot work (negative limits, an unstable loop)."""


def default_T_body_camera() -> Array:
    """Camera on top of the body looking up, its axes parallel to the body's (image x along the
    body's front, optical axis up), 15 mm ahead of and 12 mm above the body centre. With it, the
    estimate's yaw is the heading error between the body and the target."""
    return make_transform(np.eye(3), np.array([0.015, 0.0, 0.012]))


def load_T_body_camera(path: str | Path) -> Array:
    """``T_body_camera`` from a YAML file holding a 4x4 matrix under that key (body FLU: x
    forward, y left, z up; camera: OpenCV optical frame)."""
    where = Path(path)
    try:
        data = yaml.safe_load(where.read_text())
    except OSError as exc:
        raise ControllerConfigError(f"{where}: cannot read ({exc.strerror})") from exc
    except yaml.YAMLError as exc:
        raise ControllerConfigError(f"{where}: not YAML ({exc})") from exc
    if not isinstance(data, dict) or "T_body_camera" not in data:
        raise ControllerConfigError(f"{where}: no T_body_camera (a 4x4 matrix, metres)")
    try:
        return check_transform(np.asarray(data["T_body_camera"], dtype=float), "T_body_camera")
    except (ValueError, TypeError, PerchposeError) as exc:
        raise ControllerConfigError(f"{where}: T_body_camera: {exc}") from exc


@dataclass(frozen=True)
class ControllerSettings:
    """Gains and limits (SI units).

    k_xy, k_z, k_yaw : proportional gains, 1/s. align_radius_m : lateral error under which the
    vehicle climbs at full rate. commit_distance_m : height below the plate where the final
    constant-speed climb starts. commit_speed_mps : that speed. blind_commit_m : losing the
    target closer than this while aligned (the camera is then too close to see it) commits
    instead of counting as lost. hold_s : hover after losing the
    target before descending at descend_mps. camera_period_s : update period, for the stability
    check.
    """

    k_xy: float = 1.6
    k_z: float = 0.9
    k_yaw: float = 1.5
    max_xy_mps: float = 0.35
    max_z_mps: float = 0.3
    max_yaw_rate: float = 1.5
    align_radius_m: float = 0.015
    commit_distance_m: float = 0.04
    commit_speed_mps: float = 0.15
    commit_align_m: float = 0.006
    blind_commit_m: float = 0.12
    hold_s: float = 1.0
    descend_mps: float = 0.1
    camera_period_s: float = 1.0 / 30.0
    p_body_magnet_m: tuple[float, float, float] = (0.0, 0.0, 0.02)
    T_body_camera: Array = field(default_factory=default_T_body_camera)

    def __post_init__(self) -> None:
        positive = (
            "k_xy",
            "k_z",
            "k_yaw",
            "max_xy_mps",
            "max_z_mps",
            "max_yaw_rate",
            "align_radius_m",
            "commit_speed_mps",
            "descend_mps",
            "camera_period_s",
        )
        require_positive(self, positive, ControllerConfigError)
        # a proportional loop closed through a sampled, one-frame-late measurement is stable
        # only while gain * period stays well under 1
        for name in ("k_xy", "k_z", "k_yaw"):
            loop = getattr(self, name) * self.camera_period_s * 2.0
            if loop >= 0.5:
                raise ControllerConfigError(
                    f"{name} = {getattr(self, name)} /s is unstable at a "
                    f"{self.camera_period_s:.3f} s camera period with a frame of latency "
                    f"(need {name} < "
                    f"{0.25 / self.camera_period_s:.1f} /s)"
                )


@dataclass(frozen=True)
class Command:
    """A velocity setpoint in the world frame (z up), a yaw rate, and the phase."""

    v_mps: Array
    yaw_rate_rad_s: float
    phase: str
    error_m: Array | None = None


class PerchingController:
    """Steers the magnet onto the target's centre; call ``update`` once per camera frame."""

    def __init__(self, settings: ControllerSettings | None = None) -> None:
        self.settings = settings or ControllerSettings()
        self.phase = "search"
        self._lost_since: float | None = None
        self._last_error: Array | None = None

    def magnet_to_target(self, estimate: Estimate, R_world_body: Array) -> tuple[Array, float]:
        """(world-frame vector from the magnet to the target centre, heading error in rad)."""
        s = self.settings
        p_camera = np.array([estimate.x_cm, estimate.y_cm, estimate.z_cm]) / 100.0
        T = s.T_body_camera
        p_body = T[:3, :3] @ p_camera + T[:3, 3]
        d_world = R_world_body @ (p_body - np.asarray(s.p_body_magnet_m))
        yaw = math.radians(estimate.yaw_deg)
        x_target_camera = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        x_target_body = T[:3, :3] @ x_target_camera
        heading_error = math.atan2(float(x_target_body[1]), float(x_target_body[0]))
        return d_world, wrap_angle_rad(heading_error)

    def update(self, estimate: Estimate | None, t_s: float, R_world_body: Array) -> Command:
        """The setpoint for this frame; ``estimate`` None or not valid means no target."""
        s = self.settings
        if estimate is None or not estimate.valid:
            return self._no_target(t_s)
        self._lost_since = None
        d, heading_error = self.magnet_to_target(estimate, R_world_body)
        self._last_error = d
        lateral = float(np.hypot(d[0], d[1]))
        v = np.zeros(3)
        scale = min(1.0, s.max_xy_mps / max(1e-9, s.k_xy * lateral))
        v[:2] = s.k_xy * d[:2] * scale
        yaw_rate = float(np.clip(s.k_yaw * heading_error, -s.max_yaw_rate, s.max_yaw_rate))
        height = float(d[2])
        if self.phase == "commit" or (height < s.commit_distance_m and lateral < s.commit_align_m):
            self.phase = "commit"
            v[2] = s.commit_speed_mps
        else:
            aligned = float(
                np.clip(1.0 - (lateral - s.align_radius_m) / (3 * s.align_radius_m), 0.0, 1.0)
            )
            self.phase = "climb" if aligned > 0 else "align"
            v[2] = aligned * float(np.clip(s.k_z * height, s.commit_speed_mps, s.max_z_mps))
        return Command(v, yaw_rate, self.phase, d)

    def _no_target(self, t_s: float) -> Command:
        s = self.settings
        if self.phase == "commit":  # the last centimetres: the camera is too close to see
            return Command(np.array([0.0, 0.0, s.commit_speed_mps]), 0.0, "commit")
        if self.phase == "search":
            return Command(np.zeros(3), 0.0, "search")
        last = self._last_error
        if (
            self.phase in ("align", "climb")
            and last is not None
            and last[2] < s.blind_commit_m
            and float(np.hypot(last[0], last[1])) < 2 * s.align_radius_m
        ):
            self.phase = "commit"
            return Command(np.array([0.0, 0.0, s.commit_speed_mps]), 0.0, "commit")
        if self._lost_since is None:
            self._lost_since = t_s
        self.phase = "lost"
        if t_s - self._lost_since < s.hold_s:
            return Command(np.zeros(3), 0.0, "lost")
        return Command(np.array([0.0, 0.0, -s.descend_mps]), 0.0, "lost")
