"""The paper's fusion: stage 1, only the outer (largest) marker -> its pose; stage 3, only inner
markers -> their pose; stage 2, both -> per component ``sigma * outer + (1 - sigma) * inner``, yaw
on the circle. With more than one inner marker, the inner markers are averaged first. Its inputs
are the per-marker filters' poses; its weights (``FusionSigmas``) are the paper's LMS fit unless
a file (``perchpose fit-fusion --json``) gives others."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.errors import FusionFileError
from perchpose.filters.kalman import MarkerFilters
from perchpose.fusion.base import (
    STAGE_INNER,
    STAGE_NONE,
    STAGE_OUTER,
    Fused,
    stage_of,
)
from perchpose.fusion.transport import angles_covariance, camera_covariance
from perchpose.geometry import tilt_rad, weighted_circular_mean_rad
from perchpose.pose.joint import pose_covariance
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection, MarkerPose

Array = NDArray[np.float64]

SIGMA_FIELDS = ("x", "y", "z", "yaw")


@dataclass(frozen=True)
class FusionSigmas:
    """Weights of the outer marker per component (the paper's LMS fit by default)."""

    x: float = 0.275
    y: float = 0.306
    z: float = 0.728
    yaw: float = 0.469

    def __post_init__(self) -> None:
        for name in SIGMA_FIELDS:
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise ValueError(f"sigma_{name} must be in [0, 1], got {value}")

    def as_array(self) -> Array:
        """(4,) [sigma_yaw, sigma_x, sigma_y, sigma_z] in the filter's state order."""
        return np.array([self.yaw, self.x, self.y, self.z])

    def to_dict(self) -> dict[str, float]:
        """The weights by field name, as ``fit-fusion --json`` writes them."""
        return {name: float(getattr(self, name)) for name in SIGMA_FIELDS}

    @staticmethod
    def load(path: str | Path) -> FusionSigmas:
        """The weights of a JSON file with the fields ``x``, ``y``, ``z`` and ``yaw`` at its top
        level (what ``perchpose fit-fusion --json`` writes; other keys are ignored). Raises
        ``FusionFileError`` naming the file and the field at fault."""
        try:
            content = json.loads(Path(path).read_text(encoding="utf-8"))
        except FileNotFoundError as exc:
            raise FusionFileError(f"{path}: file not found") from exc
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise FusionFileError(f"{path}: not a JSON file of fusion weights ({exc})") from exc
        except RecursionError as exc:  # Python's parser recurses once per level
            raise FusionFileError(f"{path}: nested too deep to be fusion weights") from exc
        if not isinstance(content, dict):
            raise FusionFileError(f"{path}: expected an object with x, y, z and yaw")
        missing = [name for name in SIGMA_FIELDS if name not in content]
        if missing:
            raise FusionFileError(
                f"{path}: missing {', '.join(missing)} (write the file with "
                "'perchpose fit-fusion DATA --json FILE')"
            )
        values = {}
        for name in SIGMA_FIELDS:
            value = content[name]
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise FusionFileError(f"{path}: {name} must be a number, got {value!r}")
            values[name] = float(value)
        try:
            return FusionSigmas(**values)
        except ValueError as exc:
            raise FusionFileError(f"{path}: {exc}") from exc


def marker_poses(
    measurements: dict[int, MarkerPose], markers: MarkerFilters, use_filter: bool
) -> dict[int, Array]:
    """The poses that fuse: the filtered poses (``MarkerFilters.contributing``), or this
    frame's raw measurements without the filter."""
    if not use_filter:
        return {i: m.filter_z for i, m in measurements.items()}
    return markers.contributing(set(measurements))


def _mean_pose(poses: list[Array]) -> Array:
    stacked = np.stack(poses)
    out = stacked.mean(axis=0)
    out[0] = weighted_circular_mean_rad(stacked[:, 0], np.ones(len(poses)))
    return np.asarray(out)


def fuse_paper(poses: dict[int, Array], sigmas: FusionSigmas) -> tuple[Array, int]:
    """Fuse per-marker poses [psi_rad, tx_m, ty_m, tz_m] keyed by marker index.

    Returns the fused (4,) pose and the stage; an empty input gives NaNs and stage 0.
    """
    stage = stage_of(set(poses))
    if stage == STAGE_NONE:
        return np.full(4, np.nan), stage
    inner = [p for i, p in poses.items() if i > 0]
    if stage == STAGE_OUTER:
        return poses[0].copy(), stage
    inner_pose = _mean_pose(inner)
    if stage == STAGE_INNER:
        return inner_pose, stage
    s = sigmas.as_array()
    outer_pose = poses[0]
    fused = s * outer_pose + (1.0 - s) * inner_pose
    fused[0] = weighted_circular_mean_rad(
        np.array([outer_pose[0], inner_pose[0]]), np.array([s[0], 1.0 - s[0]])
    )
    return fused, stage


class PaperFusion:
    """The paper's fusion of the per-marker filters (``markers``, which the estimator advances
    each frame before it fuses: they are also each marker's record in every estimate) with
    fixed sigmas, by stage.

    With ``camera``, ``target`` and ``corner_sigma_px`` it also gives the target's tilt and a
    covariance: those of the frame's fused measurement (each measured marker's pose
    covariance from its own corners, weighed as the poses are). The paper's filters have no
    calibrated noise model, so their smoothing is not in it; a frame the filters bridge
    without a measurement has none."""

    reinitialised = 0

    def __init__(
        self,
        sigmas: FusionSigmas,
        markers: MarkerFilters,
        *,
        use_filter: bool = True,
        camera: CameraModel | None = None,
        target: TargetSpec | None = None,
        corner_sigma_px: float = 0.0,
    ) -> None:
        self.sigmas = sigmas
        self.markers = markers
        self.use_filter = use_filter
        self.camera = camera
        self.target = target
        self.corner_sigma_px = corner_sigma_px
        self._tilt: tuple[float, float] = (math.nan, math.nan)

    def _measured_uncertainty(
        self, measurements: dict[int, MarkerPose], contributing: set[int]
    ) -> tuple[tuple[float, float], Array | None] | None:
        """The weighed tilt and covariance over [roll, pitch, yaw, x, y, z] of the markers
        measured in this frame that take part, or None."""
        camera, target = self.camera, self.target
        used = {i: m for i, m in measurements.items() if i in contributing}
        if camera is None or target is None or not used or not self.corner_sigma_px > 0:
            return None
        tilts: dict[int, Array] = {}
        covariances: dict[int, Array | None] = {}
        for i, m in used.items():
            T = m.T_camera_target
            tilts[i] = np.array(tilt_rad(T[:3, :3]))
            points = target.markers[i].corners_target_m
            c = pose_covariance(camera, T, points, self.corner_sigma_px)
            covariances[i] = None if c is None else angles_covariance(T, c)
        # the inner markers are averaged first, as their poses are (``fuse_paper``)
        groups = [g for g in ([i for i in used if i == 0], [i for i in used if i > 0]) if g]
        tilt_g = [np.mean([tilts[i] for i in g], axis=0) for g in groups]
        cov_g: list[Array | None] = []
        for g in groups:
            covs = [covariances[i] for i in g]
            known = [c for c in covs if c is not None]
            cov_g.append(
                sum(known, np.zeros((6, 6))) / len(g) ** 2 if len(known) == len(g) else None
            )
        if len(groups) == 1:
            return (float(tilt_g[0][0]), float(tilt_g[0][1])), cov_g[0]
        s = self.sigmas.as_array()  # [yaw, x, y, z]: the outer marker's weights
        w = np.array([s[0], s[0], s[0], s[1], s[2], s[3]])
        tilt = w[0] * tilt_g[0] + (1.0 - w[0]) * tilt_g[1]
        cov_o, cov_i = cov_g
        if cov_o is None or cov_i is None:
            return (float(tilt[0]), float(tilt[1])), None
        W, V = np.diag(w), np.diag(1.0 - w)
        return (float(tilt[0]), float(tilt[1])), W @ cov_o @ W + V @ cov_i @ V

    def fuse(
        self,
        t_s: float,
        detections: tuple[MarkerDetection, ...],
        measurements: dict[int, MarkerPose],
    ) -> Fused:
        markers = self.markers
        poses = marker_poses(measurements, markers, self.use_filter)
        pose, stage = fuse_paper(poses, self.sigmas)
        age = 0.0 if measurements or not self.use_filter else markers.age_s(poses, t_s)
        measured = self._measured_uncertainty(measurements, set(poses))
        covariance = None
        if measured is not None:
            self._tilt, angles = measured
            if angles is not None and stage != STAGE_NONE:
                covariance = camera_covariance(float(pose[0]), self._tilt[1], angles)
        tilt = self._tilt if stage != STAGE_NONE else (math.nan, math.nan)
        return Fused(pose, stage, frozenset(poses), age, tilt, covariance)

    def predicted_pose(self, t_s: float) -> Array | None:
        return None
