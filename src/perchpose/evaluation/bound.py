"""Achieved pose error beside the Cramer-Rao bound for the measured corner noise.

At each distance the target is rendered (3 x 3 rays per pixel, 34 per ninth of a pixel at
edges) at several poses, in several frames with independent noise at each. The corner noise is
measured on those frames (detected against true corners); the bound is ``sigma^2 (J^T J)^-1``
at the true pose for the markers fully in view; the achieved error is the RMS error of the joint
pose over the frames, and of the per-marker IPPE pose of the largest marker in view (what the
paper's pipeline measures before fusing). Results are pooled over the poses of a distance.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from perchpose.detection.detector import MarkerDetector
from perchpose.geometry import facing_pose, yaw_rad
from perchpose.pose.joint import pose_covariance, solve_joint_pose, uncertainty
from perchpose.pose.marker import solve_marker_pose
from perchpose.sim.render import ImageQuality, Renderer
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection, MarkerPose


@dataclass(frozen=True)
class BoundRow:
    """One distance: the bound and the achieved RMS errors, x y z in cm and yaw in deg."""

    camera: str
    distance_m: float
    markers: tuple[int, ...]
    frames: int
    corner_sigma_px: float
    bound: tuple[float, float, float, float]
    joint: tuple[float, float, float, float]
    single: tuple[float, float, float, float]

    @property
    def ratio(self) -> float:
        """Largest ratio of the joint pose's error to the bound over x, y, z."""
        return max(j / b for j, b in zip(self.joint[:3], self.bound[:3], strict=True) if b > 0)

    @property
    def yaw_ratio(self) -> float:
        """Ratio of the joint pose's yaw error to the bound on yaw."""
        return self.joint[3] / self.bound[3] if self.bound[3] > 0 else math.nan


def _rms(errors: list[list[float]]) -> tuple[float, float, float, float]:
    e = np.array(errors)
    if e.size == 0:
        return (math.nan,) * 4
    r = np.sqrt(np.mean(e * e, axis=0))
    return (float(r[0]), float(r[1]), float(r[2]), float(r[3]))


def _errors(T: np.ndarray, truth: np.ndarray) -> list[float]:
    d = (T[:3, 3] - truth[:3, 3]) * 100.0
    yaw = math.degrees(math.remainder(yaw_rad(T[:3, :3]) - yaw_rad(truth[:3, :3]), 2 * math.pi))
    return [float(d[0]), float(d[1]), float(d[2]), yaw]


@dataclass(frozen=True)
class _PoseResult:
    markers: tuple[int, ...]
    sigma_px: np.ndarray  # per corner coordinate pair, as weighted
    bound: tuple[float, float, float, float]
    joint_err: list[list[float]]
    single_err: list[list[float]]


def _one_pose(
    renderer: Renderer[TargetSpec],
    detector: MarkerDetector,
    quality: ImageQuality,
    T: np.ndarray,
    frames: int,
    rng: np.random.Generator,
    tick: Callable[[int], None],
) -> _PoseResult | None:
    """The bound and the achieved errors at one pose, or None when nothing was detected or
    the markers detected changed between frames (a marker at the edge of detection)."""
    camera, target = renderer.camera, renderer.target
    truth_px = renderer.corners_px(T)
    corner_err: dict[int, list[float]] = {}
    single_err: list[list[float]] = []
    joint_frames: list[tuple[tuple[MarkerDetection, ...], np.ndarray]] = []
    seen: set[tuple[int, ...]] = set()
    for _ in range(frames):
        image = renderer.render(T, quality, rng)
        tick(1)
        dets = detector.detect(image).markers
        if not dets:
            continue
        seen.add(tuple(d.marker_index for d in dets))
        for d in dets:
            true = truth_px[d.marker_index]
            if true is not None:
                corner_err.setdefault(d.marker_index, []).extend(
                    (d.corners_px - true).reshape(-1).tolist()
                )
        largest = max(dets, key=lambda d: d.side_px)
        single = solve_marker_pose(
            camera, target.markers[largest.marker_index], largest.marker_index, largest.corners_px
        )
        if not isinstance(single, MarkerPose):
            continue
        single_err.append(_errors(single.T_camera_target, T))
        joint_frames.append((dets, single.T_camera_target))
    if not corner_err or len(seen) != 1:
        return None
    (used,) = seen
    # per-marker corner noise: each marker's corners weigh by their own precision
    sigmas = {i: float(np.sqrt(np.mean(np.square(corner_err[i])))) for i in used}
    points = np.concatenate([target.markers[i].corners_target_m for i in used])
    sigma = np.repeat([sigmas[i] for i in used], 4)
    # the joint pose weighted with the measured noise, frame by frame
    joint_err: list[list[float]] = []
    for dets, start in joint_frames:
        joint = solve_joint_pose(
            camera, target, dets, start, np.array([sigmas[d.marker_index] for d in dets])
        )
        if joint is not None:
            joint_err.append(_errors(joint.T_camera_target, T))
    cov = pose_covariance(camera, T, points, sigma)
    if cov is None:
        return None
    u = uncertainty(T, cov)
    bound = (100 * u.x_m, 100 * u.y_m, 100 * u.z_m, math.degrees(u.yaw_rad))
    return _PoseResult(used, sigma, bound, joint_err, single_err)


def bound_rows(
    renderer: Renderer[TargetSpec],
    quality: ImageQuality,
    distances_m: tuple[float, ...],
    frames: int,
    rng: np.random.Generator,
    tick: Callable[[int], None],
    poses: int = 1,
) -> list[BoundRow]:
    """The bound and the achieved errors at each distance: ``poses`` poses (random heading),
    ``frames`` frames each. Pooled over the poses: the bound as the RMS of the poses' bounds,
    the achieved errors as the RMS over all frames (one pose alone also measures how that
    pose's corners happen to be biased)."""
    camera = renderer.camera
    detector = MarkerDetector(camera, renderer.target)
    rows = []
    for z in distances_m:
        results = []
        for _ in range(poses):
            T = facing_pose(0.04 * z, -0.03 * z, z, float(rng.uniform(-math.pi, math.pi)))
            result = _one_pose(renderer, detector, quality, T, frames, rng, tick)
            if result is not None:
                results.append(result)
        if not results:
            continue
        bound = np.sqrt(np.mean(np.square([r.bound for r in results]), axis=0))
        sigma = np.concatenate([r.sigma_px for r in results])
        rows.append(
            BoundRow(
                camera.name,
                float(z),
                tuple(sorted({i for r in results for i in r.markers})),
                sum(len(r.joint_err) for r in results),
                float(np.sqrt(np.mean(np.square(sigma)))),
                (float(bound[0]), float(bound[1]), float(bound[2]), float(bound[3])),
                _rms([e for r in results for e in r.joint_err]),
                _rms([e for r in results for e in r.single_err]),
            )
        )
    return rows


def bound_markdown(rows: list[BoundRow]) -> str:
    """The report's section on the physical limit."""
    lines = [
        "",
        "## Against the physical limit (Cramer-Rao bound)",
        "",
        "Per distance: poses with random headings, frames with independent noise at each (3 x "
        "3 rays per pixel, 34 per ninth of a pixel at edges), pooled: the bound is the RMS of the "
        "poses' bounds, the errors the RMS over all frames. Corner noise: per-axis RMS of the "
        "detected corners against the true ones, per marker (the table shows their RMS). "
        "Bound: standard deviation of an unbiased pose from those corners. Achieved: RMS error "
        "of the joint pose from all corners (weighted by the measured noise), and of the "
        "largest marker's pose alone. x, y, z in cm, yaw in deg. Joint / bound: the largest "
        "ratio over "
        "x, y and z, and the ratio on yaw.",
        "",
        "| camera | z (m) | markers | frames | corner noise (px) | bound x/y/z, yaw | "
        "joint x/y/z, yaw | joint / bound, position | joint / bound, yaw | "
        "largest marker alone x/y/z, yaw |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]

    def quad(v: tuple[float, float, float, float]) -> str:
        return f"{v[0]:.3f}/{v[1]:.3f}/{v[2]:.3f}, {v[3]:.3f}"

    for r in rows:
        lines.append(
            f"| {r.camera} | {r.distance_m:.2f} | {','.join(map(str, r.markers))} | {r.frames} | "
            f"{r.corner_sigma_px:.3f} | {quad(r.bound)} | {quad(r.joint)} | {r.ratio:.2f} | "
            f"{r.yaw_ratio:.2f} | {quad(r.single)} |"
        )
    return "\n".join(lines) + "\n"
