"""Whether corners fitted without a detection show the marker they are meant to: its cells read
back through the corners.

Tracking fits a marker's corners straight from where it is predicted, without OpenCV's quad
search and decoding. That answer is kept only if the image inside the fitted corners is the
marker's printed pattern in the predicted orientation: each cell whose whole area is one shade
in the print (the target's ``albedo``: border cells, the marker's own bits, anything else
printed on it) is sampled near its centre, and the cells must split by brightness as printed.
A fit that slid onto another edge (by a cell or more), a quad turned by a quarter, or another
marker, puts black cells where white ones belong and fails.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.camera.lens import Lens, lens_normalize, lens_project
from perchpose.corners.edge_geometry import bilinear_points
from perchpose.numeric.jit import compiled
from perchpose.numeric.linalg import homography_of_4, through_homography
from perchpose.target import TargetSpec

Array = NDArray[np.float64]

# Sub-samples across each cell, per axis, at these fractions of a cell from its centre: the
# mean over them is steadier than one pixel under noise and interference.
_SUB_CELL = (-0.2, 0.0, 0.2)
# A cell is used where the print is one shade over this grid across it (fractions of a cell;
# fine enough not to step over the border of a marker nested in it).
_UNIFORM_GRID = np.linspace(0.02, 0.98, 25)


@dataclass(frozen=True)
class CellPattern:
    """The cells of one marker that are one shade in the print: their centres in the marker's
    cell coordinates (``uv`` (P, 2): u from corner 0 towards corner 1, v from corner 0 towards
    corner 3, the marker spanning [0, n]), whether each is white, and n."""

    uv: Array
    white: NDArray[np.bool_]
    n_cells: int

    @staticmethod
    def of(target: TargetSpec, index: int) -> CellPattern:
        """The uniform cells of marker ``index`` of ``target``, with what else is printed on
        them (a marker nested in another makes the larger one's cells under it mixed)."""
        marker = target.markers[index]
        n = int(marker.cells.shape[0])
        cell_m = marker.side_m / n
        rows, cols = np.mgrid[0:n, 0:n]
        fu, fv = np.meshgrid(_UNIFORM_GRID, _UNIFORM_GRID)
        u = cols.reshape(-1, 1) + fu.reshape(1, -1)  # (n*n, G)
        v = rows.reshape(-1, 1) + fv.reshape(1, -1)
        x_m, y_m = (u - n / 2.0) * cell_m, (n / 2.0 - v) * cell_m  # marker frame, y up
        T = marker.T_target_marker
        xt = T[0, 0] * x_m + T[0, 1] * y_m + T[0, 3]
        yt = T[1, 0] * x_m + T[1, 1] * y_m + T[1, 3]
        shade = target.albedo(xt, yt)
        uniform = np.all(shade == shade[:, :1], axis=1) & np.isfinite(shade[:, 0])
        centres = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], axis=1)
        return CellPattern(centres[uniform], shade[uniform, 0] > 0.5, n)

    @cached_property
    def both_shades(self) -> bool:
        """Whether the cells hold both shades (else there is nothing to read them against)."""
        return bool(np.any(self.white) and not np.all(self.white))

    @cached_property
    def samples_uv(self) -> Array:
        """Where each cell is sampled (P * S, 2; cell coordinates): ``_SUB_CELL`` around its
        centre on both axes, the cells one after the other."""
        du, dv = np.meshgrid(_SUB_CELL, _SUB_CELL)
        offsets = np.stack([du.ravel(), dv.ravel()], axis=1)  # (S, 2)
        return np.ascontiguousarray((self.uv[:, None, :] + offsets[None, :, :]).reshape(-1, 2))


@dataclass(frozen=True)
class CellReading:
    """What the image shows in a pattern's cells: how many read as the other shade, out of how
    many, and the black and white cells' mean grey levels."""

    wrong: int
    cells: int
    black_level: float
    white_level: float

    def matches(self, max_wrong_fraction: float = 0.1, min_contrast: float = 10.0) -> bool:
        """Whether the cells read as printed: white brighter than black by ``min_contrast``
        grey levels, and at most ``max_wrong_fraction`` of them (at least one) on the wrong
        side of the level halfway between."""
        allowed = max(1, int(max_wrong_fraction * self.cells))
        return self.white_level - self.black_level >= min_contrast and self.wrong <= allowed


def read_cells(
    grey: NDArray[np.uint8], corners_px: Array, camera: CameraModel, pattern: CellPattern
) -> CellReading | None:
    """The cells of ``pattern`` read from ``grey`` inside ``corners_px`` (4, 2; ArUco order,
    corner 0 at the marker's top left as printed), through the lens model; None where the
    corners make no quad or a cell falls outside the image."""
    if not pattern.both_shades:
        return None
    corners = np.ascontiguousarray(np.asarray(corners_px, np.float64).reshape(4, 2))
    read, wrong, black, white = _read_compiled(
        camera.compiled_lens,
        grey,
        corners,
        float(pattern.n_cells),
        pattern.samples_uv,
        pattern.white,
    )
    return CellReading(wrong, len(pattern.white), black, white) if read else None


@compiled
def _read_compiled(
    lens: Lens,
    grey: NDArray[np.uint8],
    corners_px: Array,
    n: float,
    samples_uv: Array,
    white: NDArray[np.bool_],
) -> tuple[bool, int, float, float]:
    """``read_cells`` through the lens of ``CameraModel.compiled_lens``: (whether the cells
    could be read, then ``_cell_levels``' answer)."""
    read, px = cell_points_px(lens, corners_px, n, samples_uv)
    if not read:
        return False, 0, 0.0, 0.0
    wrong, black, bright = _cell_levels(bilinear_points(grey, px), white)
    if not (math.isfinite(black) and math.isfinite(bright)):
        return False, 0, 0.0, 0.0
    return True, wrong, black, bright


@compiled
def cell_points_px(lens: Lens, corners_px: Array, n: float, points_uv: Array) -> tuple[bool, Array]:
    """(whether they could be placed, the pixels (P, 2) of ``points_uv`` (P, 2) in the cell
    coordinates of a marker of ``n`` cells whose corners are ``corners_px`` (4, 2; ArUco
    order)): through the homography of the corners on the lens's normalised plane, then the
    lens."""
    kind, K, d = lens
    corners_n = lens_normalize(kind, corners_px, K, d)
    if not np.isfinite(corners_n).all():
        return False, np.empty((0, 2))
    square = np.array([[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]])
    found, H = homography_of_4(square, corners_n)
    if not found:
        return False, np.empty((0, 2))
    on_plane = through_homography(H, points_uv)
    rays = np.ones((on_plane.shape[0], 3))
    rays[:, :2] = on_plane
    px, in_front = lens_project(kind, rays, K, d)
    return bool(in_front.all()), px


@compiled
def _cell_levels(values: Array, white: NDArray[np.bool_]) -> tuple[int, float, float]:
    """From ``values`` (P * S: S samples of each of P cells, one cell after the other): how
    many cells read as the other shade than ``white`` (P,) says (against the level halfway
    between), the black cells' and the white cells' mean level (NaN where a sample is)."""
    P = white.shape[0]
    S = values.shape[0] // P
    level = np.empty(P)
    black_sum = white_sum = 0.0
    n_white = 0
    for p in range(P):
        total = 0.0
        for s in range(S):
            total += values[p * S + s]
        level[p] = total / S
        if white[p]:
            white_sum += level[p]
            n_white += 1
        else:
            black_sum += level[p]
    black, bright = black_sum / (P - n_white), white_sum / n_white
    middle = 0.5 * (black + bright)
    wrong = 0
    for p in range(P):
        if (level[p] > middle) != white[p]:
            wrong += 1
    return wrong, black, bright
