"""Scenarios: sequences of target poses with timestamps, image quality and dropouts."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.errors import ScenarioError
from perchpose.geometry import facing_pose, wrap_angle_rad
from perchpose.sim.render import ImageQuality
from perchpose.target import TargetSpec
from perchpose.values import quad_side_px

Array = NDArray[np.float64]

# The smallest marker side, in pixels, that counts as "in view" for the truth's stage.
MIN_SIDE_IN_VIEW_PX = 12.0
# Corners must lie this far inside the image border to count as in view.
BORDER_MARGIN_PX = 3.0


@dataclass(frozen=True)
class Scenario:
    """A rendered sequence's truth.

    t_s : (N,) seconds. poses : (N, 4, 4) T_camera_target, metres.
    dropout : (N,) bool, frames where the target is hidden (occluded).
    """

    name: str
    t_s: Array
    poses: NDArray[np.float64]
    dropout: NDArray[np.bool_]
    quality: ImageQuality

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


def markers_in_view(
    camera: CameraModel, target: TargetSpec, T_camera_target: Array
) -> tuple[bool, ...]:
    """For each marker: all four corners inside the image and its side at least 12 px."""
    out = []
    for m in target.markers:
        p = (T_camera_target[:3, :3] @ m.corners_target_m.T).T + T_camera_target[:3, 3]
        uv, ok = camera.project(p)
        inside = bool(np.all(ok)) and camera.in_image(uv, BORDER_MARGIN_PX)
        side = quad_side_px(uv) if inside else 0.0
        out.append(inside and side >= MIN_SIDE_IN_VIEW_PX)
    return tuple(out)


def approach(
    duration_s: float = 8.0,
    fps: float = 30.0,
    start_z_m: float = 1.5,
    contact_z_m: float = 0.03,
    dropouts: tuple[tuple[float, float], ...] = ((2.5, 0.2), (5.0, 0.5)),
    quality: ImageQuality | None = None,
) -> Scenario:
    """An approach from ``start_z_m`` to ``contact_z_m`` with lateral motion and a yaw that
    crosses +/-180 deg, and dropouts given as (start_s, length_s) windows.

    The lateral offset shrinks with the distance so the target stays in view; the approach
    slows near contact like a perching drone.
    """
    if duration_s <= 0 or fps <= 0:
        raise ScenarioError("duration and fps must be positive")
    if not 0 < contact_z_m < start_z_m:
        raise ScenarioError("need 0 < contact_z_m < start_z_m")
    n = max(2, int(round(duration_s * fps)))
    t = np.arange(n) / fps
    s = t / t[-1]
    # smooth approach: fast far away, slow at contact
    z = contact_z_m + (start_z_m - contact_z_m) * (1.0 - s) ** 1.6
    lateral = 0.12 * z
    x = lateral * np.sin(2 * math.pi * 0.31 * t + 0.4)
    y = 0.8 * lateral * np.cos(2 * math.pi * 0.23 * t)
    yaw = np.array([wrap_angle_rad(math.radians(150.0 + 70.0 * si)) for si in s])
    tilt_x = np.radians(4.0) * np.sin(2 * math.pi * 0.4 * t)
    tilt_y = np.radians(3.0) * np.cos(2 * math.pi * 0.5 * t)
    poses = np.stack(
        [
            facing_pose(
                float(x[i]),
                float(y[i]),
                float(z[i]),
                float(yaw[i]),
                float(tilt_x[i]),
                float(tilt_y[i]),
            )
            for i in range(n)
        ]
    )
    dropout = np.zeros(n, bool)
    for start, length in dropouts:
        dropout |= (t >= start) & (t < start + length)
    return Scenario("approach", t, poses, dropout, quality or ImageQuality())


def random_motion(
    seed: int,
    duration_s: float = 5.0,
    fps: float = 30.0,
    centre: tuple[float, float, float, float] = (0.0, 0.0, 0.8, 0.3),
    q: tuple[float, float, float, float] = (0.05, 0.05, 0.05, 0.5),
    spring_rad_s: float = 1.0,
    quality: ImageQuality | None = None,
) -> Scenario:
    """A target that moves as the fused pose's filter assumes a target moves: white-noise
    acceleration of spectral densities ``q`` (x, y, z in m^2/s^3, yaw in rad^2/s^3; the
    defaults are ``CovarianceFilterSettings``'), held about ``centre`` (x, y, z in m, yaw in
    rad) by a weak spring of ``spring_rad_s`` (damping 0.7) so that it stays in view: with the
    defaults each axis wanders by about 13 cm (yaw by 0.4 rad) about the centre, while over a
    frame's few tens of milliseconds it moves as the filter's model. A fixed tilt of a couple
    of degrees; integrated at 20 steps a frame; seeded."""
    if duration_s <= 0 or fps <= 0 or spring_rad_s <= 0 or min(q) < 0:
        raise ScenarioError("duration, fps and spring must be positive and q not negative")
    n = max(2, int(round(duration_s * fps)))
    rng = np.random.default_rng(seed)
    sub = 20
    dt = 1.0 / (fps * sub)
    home = np.array([centre[3], centre[0], centre[1], centre[2]])  # yaw, x, y, z
    kick = np.sqrt(np.array([q[3], q[0], q[1], q[2]]) / dt)
    p, v = home.copy(), np.zeros(4)
    poses = []
    for _ in range(n):
        for _ in range(sub):
            a = -(spring_rad_s**2) * (p - home) - 1.4 * spring_rad_s * v
            v = v + (a + kick * rng.standard_normal(4)) * dt
            p = p + v * dt
        poses.append(facing_pose(p[1], p[2], p[3], wrap_angle_rad(p[0]), 0.03, -0.02))
    t = np.arange(n) / fps
    return Scenario(
        "random motion", t, np.stack(poses), np.zeros(n, bool), quality or ImageQuality()
    )


def static_grid(
    frames_per_pose: int = 5,
    fps: float = 30.0,
    z_m: tuple[float, ...] = (0.12, 0.2, 0.35, 0.6, 1.0, 1.5),
    offsets: tuple[float, ...] = (-0.25, 0.0, 0.25),
    yaws_deg: tuple[float, ...] = (0.0, 90.0, -160.0),
    quality: ImageQuality | None = None,
) -> Scenario:
    """A grid of static poses: for each distance, lateral offsets as a fraction of the distance
    and headings; each pose is held for ``frames_per_pose`` frames."""
    if frames_per_pose < 1:
        raise ScenarioError("frames_per_pose must be >= 1")
    poses = []
    for z in z_m:
        for ox in offsets:
            for oy in offsets:
                for yaw in yaws_deg:
                    T = facing_pose(ox * z, oy * z * 0.75, z, math.radians(yaw))
                    poses.extend([T] * frames_per_pose)
    n = len(poses)
    return Scenario(
        "static", np.arange(n) / fps, np.stack(poses), np.zeros(n, bool), quality or ImageQuality()
    )


SCENARIOS = ("approach", "static")


def scenario_by_name(name: str, quality: ImageQuality | None = None) -> Scenario:
    """Build a named scenario with its default settings."""
    if name == "approach":
        return approach(quality=quality)
    if name == "static":
        return static_grid(quality=quality)
    raise ScenarioError(f"unknown scenario {name!r} (choose {', '.join(SCENARIOS)})")


def truncated(scenario: Scenario, max_frames: int) -> Scenario:
    """The first ``max_frames`` frames of ``scenario``."""
    if max_frames < 1:
        raise ScenarioError(f"--frames must be >= 1, got {max_frames}")
    k = min(max_frames, len(scenario))
    return Scenario(
        scenario.name, scenario.t_s[:k], scenario.poses[:k], scenario.dropout[:k], scenario.quality
    )


def spread_board_poses(
    camera: CameraModel,
    board_width_m: float,
    n: int,
    rng: np.random.Generator,
    width_px: tuple[float, float] = (110.0, 180.0),
    field: float = 0.95,
    max_tilt_deg: float = 35.0,
) -> list[Array]:
    """``n`` poses (T_camera_target, metres) of a calibration board ``board_width_m`` wide,
    as a person waves one in front of a camera: about ``width_px`` across (at the focal length
    of the image centre), centred anywhere in the middle ``field`` of the image (to the edges of
    a fisheye's view), turned up to 0.5 rad and tilted up to ``max_tilt_deg`` about both axes."""
    poses = []
    size = np.array([camera.width_px, camera.height_px], np.float64)
    for _ in range(n):
        z_m = camera.K[0, 0] * board_width_m / rng.uniform(*width_px)
        uv = (0.5 + field * rng.uniform(-0.5, 0.5, (1, 2))) * size
        ray = camera.pixel_rays(uv)[0]
        centre = ray / np.linalg.norm(ray) * z_m
        tilt = math.radians(max_tilt_deg)
        poses.append(
            facing_pose(
                float(centre[0]),
                float(centre[1]),
                float(centre[2]),
                rng.uniform(-0.5, 0.5),
                rng.uniform(-tilt, tilt),
                rng.uniform(-tilt, tilt),
            )
        )
    return poses
