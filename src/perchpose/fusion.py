"""Fusion of the per-marker poses: the paper's three stages and sigma weights.

Stage 1: only the outer (largest) marker -> its pose. Stage 3: only inner markers -> their pose.
Stage 2: both -> per component ``sigma * outer + (1 - sigma) * inner``, yaw on the circle.
With more than one inner marker, the inner markers are averaged first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.geometry import weighted_circular_mean_rad

Array = NDArray[np.float64]

STAGE_NONE, STAGE_OUTER, STAGE_BOTH, STAGE_INNER = 0, 1, 2, 3


@dataclass(frozen=True)
class FusionSigmas:
    """Weights of the outer marker per component (the paper's LMS fit by default)."""

    x: float = 0.275
    y: float = 0.306
    z: float = 0.728
    yaw: float = 0.469

    def __post_init__(self) -> None:
        for name in ("x", "y", "z", "yaw"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise ValueError(f"sigma_{name} must be in [0, 1], got {value}")

    def as_array(self) -> Array:
        """(4,) [sigma_yaw, sigma_x, sigma_y, sigma_z] in the filter's state order."""
        return np.array([self.yaw, self.x, self.y, self.z])


def stage_of(indices: set[int] | frozenset[int]) -> int:
    """The paper's stage for the set of contributing marker indices (0 is the outer one)."""
    if not indices:
        return STAGE_NONE
    has_outer = 0 in indices
    has_inner = any(i > 0 for i in indices)
    if has_outer and has_inner:
        return STAGE_BOTH
    return STAGE_OUTER if has_outer else STAGE_INNER


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
