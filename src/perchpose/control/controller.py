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

The final climb is entered only on consistent evidence: ``commit_frames`` valid frames in a
row that put the magnet within ``commit_distance_m`` below the target and ``commit_align_m``
of its centre, or, when the camera loses the target (too close to see it), that many valid
frames in a row within ``blind_commit_m`` and twice the align radius. A valid estimate during
the climb that puts the target further than ``commit_exit_m`` above or ``commit_exit_lateral_m``
aside ends it (one outlier frame can neither start nor hold a final climb), and a final climb
that has run ``commit_timeout_s`` without the vehicle's own contact check ending it backs off
(``lost``: hold, then descend to re-acquire). An estimate older than ``max_estimate_age_s`` or
with a non-finite field counts as no target.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from perchpose.control.mount import default_T_body_camera
from perchpose.errors import ControllerConfigError, require_positive
from perchpose.geometry import wrap_angle_rad
from perchpose.values import Estimate

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ControllerSettings:
    """Gains and limits (SI units).

    k_xy, k_z, k_yaw : proportional gains, 1/s. align_radius_m : lateral error under which the
    vehicle climbs at full rate. commit_distance_m : height below the plate where the final
    constant-speed climb starts. commit_speed_mps : that speed. blind_commit_m : losing the
    target closer than this while aligned (the camera is then too close to see it) commits
    instead of counting as lost. commit_frames : consecutive valid frames that must agree
    before the final climb starts. commit_exit_m, commit_exit_lateral_m : a valid estimate
    putting the target further above or aside than these ends the final climb.
    commit_timeout_s : a final climb still going after this long backs off.
    max_estimate_age_s : estimates older than this (``Estimate.age_s`` plus the time since
    capture) are ignored. hold_s : hover after losing the target before descending at
    descend_mps. camera_period_s : update period, for the stability check.
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
    commit_frames: int = 3
    commit_exit_m: float = 0.10
    commit_exit_lateral_m: float = 0.03
    commit_timeout_s: float = 2.0
    max_estimate_age_s: float = 0.5
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
            "commit_exit_m",
            "commit_exit_lateral_m",
            "commit_timeout_s",
            "max_estimate_age_s",
        )
        require_positive(self, positive, ControllerConfigError)
        if self.commit_frames < 1:
            raise ControllerConfigError(f"commit_frames must be >= 1, got {self.commit_frames}")
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


def usable(estimate: Estimate | None, t_s: float, max_age_s: float) -> bool:
    """A valid estimate with finite fields, at most ``max_age_s`` old at ``t_s`` (its own age
    plus the time since its frame was captured)."""
    if estimate is None or not estimate.valid or not estimate.finite:
        return False
    age = estimate.age_s + max(0.0, t_s - estimate.t_s)
    return math.isfinite(age) and age <= max_age_s


class PerchingController:
    """Steers the magnet onto the target's centre; call ``update`` once per camera frame."""

    def __init__(self, settings: ControllerSettings | None = None) -> None:
        self.settings = settings or ControllerSettings()
        self.phase = "search"
        self._lost_since: float | None = None
        self._commit_since: float | None = None
        # world-frame magnet-to-target vectors of the latest valid frames, newest last
        self._recent: deque[Array] = deque(maxlen=self.settings.commit_frames)

    def magnet_to_target(self, estimate: Estimate, R_world_body: Array) -> tuple[Array, float]:
        """(world-frame vector from the magnet to the target centre, heading error in rad)."""
        s = self.settings
        p_camera = estimate.t_m
        T = s.T_body_camera
        p_body = T[:3, :3] @ p_camera + T[:3, 3]
        d_world = R_world_body @ (p_body - np.asarray(s.p_body_magnet_m))
        yaw = estimate.yaw_rad
        x_target_camera = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        x_target_body = T[:3, :3] @ x_target_camera
        heading_error = math.atan2(float(x_target_body[1]), float(x_target_body[0]))
        return d_world, wrap_angle_rad(heading_error)

    def _all_recent(self, height_m: float, lateral_m: float) -> bool:
        """The last ``commit_frames`` valid frames all had the target under ``height_m`` above
        and ``lateral_m`` aside."""
        return len(self._recent) == self.settings.commit_frames and all(
            float(d[2]) < height_m and float(np.hypot(d[0], d[1])) < lateral_m for d in self._recent
        )

    def _enter_commit(self, t_s: float) -> None:
        if self.phase != "commit":
            self._commit_since = t_s
        self.phase = "commit"

    def back_off(self, t_s: float) -> None:
        """Abandon the final climb (no contact came): hold, then descend to re-acquire."""
        self.phase = "lost"
        self._commit_since = None
        self._lost_since = t_s
        self._recent.clear()

    def update(self, estimate: Estimate | None, t_s: float, R_world_body: Array) -> Command:
        """The setpoint for this frame; an estimate that is None, not valid, not finite or too
        old means no target."""
        s = self.settings
        since = self._commit_since
        if self.phase == "commit" and since is not None and t_s - since >= s.commit_timeout_s:
            self.back_off(t_s)
        if not usable(estimate, t_s, s.max_estimate_age_s):
            return self._no_target(t_s)
        assert estimate is not None
        self._lost_since = None
        d, heading_error = self.magnet_to_target(estimate, R_world_body)
        if estimate.age_s <= 0.0:  # a measurement of this frame, not a coasting filter's guess
            self._recent.append(d)
        lateral = float(np.hypot(d[0], d[1]))
        v = np.zeros(3)
        scale = min(1.0, s.max_xy_mps / max(1e-9, s.k_xy * lateral))
        v[:2] = s.k_xy * d[:2] * scale
        yaw_rate = float(np.clip(s.k_yaw * heading_error, -s.max_yaw_rate, s.max_yaw_rate))
        height = float(d[2])
        if self.phase == "commit" and (
            height > s.commit_exit_m or lateral > s.commit_exit_lateral_m
        ):
            self.phase = "align"  # the evidence says the target is not where the climb is
            self._commit_since = None
        if self.phase == "commit" or self._all_recent(s.commit_distance_m, s.commit_align_m):
            self._enter_commit(t_s)
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
        if self.phase in ("align", "climb") and self._all_recent(
            s.blind_commit_m, 2 * s.align_radius_m
        ):
            self._enter_commit(t_s)
            return Command(np.array([0.0, 0.0, s.commit_speed_mps]), 0.0, "commit")
        if self._lost_since is None:
            self._lost_since = t_s
        self.phase = "lost"
        self._recent.clear()
        if t_s - self._lost_since < s.hold_s:
            return Command(np.zeros(3), 0.0, "lost")
        return Command(np.array([0.0, 0.0, -s.descend_mps]), 0.0, "lost")
