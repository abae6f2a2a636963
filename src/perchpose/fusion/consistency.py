"""Do the markers of one frame agree? A chi-square test of their poses against their
covariances, so that a marker whose corners are wrong (a strip of shadow along its edge, a
target file whose sizes do not match the print) is dropped rather than fused."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.pose.joint import pose_covariance
from perchpose.target import TargetSpec
from perchpose.values import MarkerPose

Array = NDArray[np.float64]

# Squared Mahalanobis distance between two markers' positions beyond which they cannot be
# measurements of one target: ten standard deviations. On rendered approaches the largest
# value is far below it (see tests/test_consistency.py); a 5 mm shadow along the outer marker's
# edge at 35 cm, or a size off by a factor of two, is far above it.
DISAGREE_CHI2 = 100.0


@dataclass(frozen=True)
class Disagreement:
    """Two markers whose positions are ``chi2`` squared standard deviations apart."""

    reference: int
    other: int
    chi2: float


def position_covariance(
    camera: CameraModel, target: TargetSpec, pose: MarkerPose, sigma_px: float
) -> Array | None:
    """(3, 3) covariance of the target centre measured from one marker's four corners with
    corner noise ``sigma_px``, metres squared (None if degenerate)."""
    corners = target.markers[pose.marker_index].corners_target_m
    cov = pose_covariance(camera, pose.T_camera_target, corners, sigma_px)
    return None if cov is None else np.asarray(cov[3:, 3:])


def position_chi2(a: Array, cov_a: Array, b: Array, cov_b: Array) -> float:
    """Squared Mahalanobis distance between two independent position measurements."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    return float(d @ np.linalg.solve(cov_a + cov_b, d))


def disagreements(
    camera: CameraModel,
    target: TargetSpec,
    measurements: dict[int, MarkerPose],
    sigma_px: float | Mapping[int, float],
    gate_chi2: float = DISAGREE_CHI2,
) -> list[Disagreement]:
    """Every measured marker whose position disagrees with the largest measured marker's;
    ``sigma_px``: the corner noise, one value or one per marker index."""
    if len(measurements) < 2:
        return []

    def sigma_of(index: int) -> float:
        return float(sigma_px) if isinstance(sigma_px, (int, float)) else sigma_px[index]

    reference = min(measurements)
    ref = measurements[reference]
    cov_ref = position_covariance(camera, target, ref, sigma_of(reference))
    if cov_ref is None:
        return []
    found = []
    for index, pose in measurements.items():
        if index == reference:
            continue
        cov = position_covariance(camera, target, pose, sigma_of(index))
        if cov is None:
            continue
        chi2 = position_chi2(ref.t_m, cov_ref, pose.t_m, cov)
        if chi2 > gate_chi2:
            found.append(Disagreement(reference, index, chi2))
    return found
