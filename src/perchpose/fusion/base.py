"""What every fusion shares: the paper's stages, ``Fused`` (a frame's fused pose) and the
``Fusion`` interface the estimator calls."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from perchpose.values import MarkerDetection, MarkerPose

Array = NDArray[np.float64]

STAGE_NONE, STAGE_OUTER, STAGE_BOTH, STAGE_INNER = 0, 1, 2, 3


def stage_of(indices: set[int] | frozenset[int]) -> int:
    """The paper's stage for the set of contributing marker indices (0 is the outer one)."""
    if not indices:
        return STAGE_NONE
    has_outer = 0 in indices
    has_inner = any(i > 0 for i in indices)
    if has_outer and has_inner:
        return STAGE_BOTH
    return STAGE_OUTER if has_outer else STAGE_INNER


@dataclass(frozen=True)
class Fused:
    """A frame's fused pose: ``pose`` (4,) [psi_rad, x_m, y_m, z_m] (NaN when there is none),
    the paper's ``stage``, the markers whose poses took part, and ``age_s``, the time since the
    newest measurement behind it (0 for a measured frame). ``tilt_rad``: (roll, pitch) of the
    target's plane (``geometry.tilt_rad``; NaN when unknown). ``covariance``: (6, 6) over
    [x, y, z] (m) and a small rotation vector about the camera's axes (rad), or None."""

    pose: Array
    stage: int
    contributing: frozenset[int]
    age_s: float
    tilt_rad: tuple[float, float] = (math.nan, math.nan)
    covariance: Array | None = None


class Fusion(Protocol):
    """How a frame's markers become one pose. Each strategy keeps the state it needs: the
    covariance fusion its filter of the fused pose and which markers it still tracks; the
    paper fusion reads the per-marker filters it was built on, which the estimator advances
    before calling ``fuse``."""

    @property
    def reinitialised(self) -> int:
        """Restarts of the strategy's own filter."""
        ...

    def fuse(
        self,
        t_s: float,
        detections: tuple[MarkerDetection, ...],
        measurements: dict[int, MarkerPose],
    ) -> Fused:
        """The fused pose of the frame at ``t_s``."""
        ...

    def predicted_pose(self, t_s: float) -> Array | None:
        """[psi, x, y, z] the strategy's own filter expects at ``t_s``; None without one."""
        ...
