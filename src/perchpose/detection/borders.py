"""Whether a marker's fitted corners sit on its own printed edge on every side: each side's
black border measured against the others.

Something dark lying flush against a marker's edge (a shadow, a strip of tape, the frame the
print is mounted in) extends the black border outwards; the fitted edge follows it, and the
marker looks larger than it is, so the pose comes out short (a 5 mm strip beside the 150 mm
outer marker: 3 to 9 % at 1.5-2.5 m) with nothing in its four corners to show it. The border's
inner edge, where it meets the marker's white cells, is still where it was printed. Its
distance from the fitted outer edge, in cells of the fitted quad (``border_widths``), is one
cell on every side of a true fit; it is measured on profiles across that inner edge through
every white cell of the ring inside the border, averaged per side. Blur and the lens widen or
narrow all four sides alike, so each side is compared with the median of the others
(``odd_border``): a side clearly wider than the rest is the fit's, not the print's. That side
is moved in by the difference (``moved_in``), through the quad's own homography, and its two
corners' covariance grows by the move, so that the pose's reported uncertainty covers what the
correction may have missed. A side that reads narrower is not taken as evidence: glare
blooming over the edge and motion blur make that on rendered frames whose corners are right.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.camera.lens import Lens
from perchpose.corners.edge_geometry import bilinear_points
from perchpose.detection.verification import CellPattern, cell_points_px
from perchpose.numeric.jit import compiled
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection

Array = NDArray[np.float64]

# each profile: from this far inside the white cell (negative, cells) across the border's inner
# edge to as far into the border; the ends give the two levels
PROFILE_CELLS = np.linspace(-0.75, 0.75, 25)
LEVEL_BEYOND_CELLS = 0.45  # samples further than this from the edge give the levels
ALONG_CELLS = (-0.15, 0.15)  # profiles per white cell, across it
# a side whose border is wider than the other sides' median by more than this (cells of the
# fitted quad) is not where the marker's edge is printed. On rendered frames without anything
# at the edge the sides differ by at most 0.06 cells (analog FPV video, cells of 3.5 px), a
# 3 mm strip beside the 150 mm marker (an eighth of its 25 mm cells) makes 0.05-0.2.
ODD_BORDER_CELLS = 0.06
ODD_BORDER_SIGMAS = 4.0  # and by this many standard errors of the difference
# cells smaller than this are not measured: on the real photos of ../shared/data (ChArUco
# markers of 3-4 px cells) borders read up to 0.2 cells uneven with nothing at their edges
MIN_CELL_PX = 4.0
SIDE_NAMES = ("top", "right", "bottom", "left")  # from corner 0 towards 1, 1-2, 2-3, 3-0


@dataclass(frozen=True)
class BorderProfiles:
    """Where a marker's border is measured: the sample points of every profile (P * S, 2;
    the marker's cell coordinates, u from corner 0 towards corner 1, v from corner 0 towards
    corner 3, S = len(PROFILE_CELLS) points from the white cell into the border) and each
    profile's side (P,: 0 top, 1 right, 2 bottom, 3 left)."""

    points_uv: Array
    side: NDArray[np.int64]
    n_cells: int

    @staticmethod
    def of(target: TargetSpec, index: int) -> BorderProfiles:
        """The profiles of marker ``index`` of ``target``: through each white cell (one shade
        in the print) of the ring inside its border whose border cell beside it is black."""
        pattern = CellPattern.of(target, index)
        n = pattern.n_cells
        shade = {
            (int(u), int(v)): bool(w) for (u, v), w in zip(pattern.uv, pattern.white, strict=True)
        }
        lines: list[tuple[int, float, float, float, float]] = []  # side, edge point, inward
        for (c, r), white in sorted(shade.items()):
            if not white:
                continue
            for side, inside, border, edge, inward in (
                (0, r == 1, (c, 0), (c + 0.5, 1.0), (0.0, 1.0)),
                (1, c == n - 2, (n - 1, r), (n - 1.0, r + 0.5), (-1.0, 0.0)),
                (2, r == n - 2, (c, n - 1), (c + 0.5, n - 1.0), (0.0, -1.0)),
                (3, c == 1, (0, r), (1.0, r + 0.5), (1.0, 0.0)),
            ):
                if inside and shade.get(border) is False:
                    lines.append((side, *edge, *inward))
        points: list[Array] = []
        sides: list[int] = []
        for side, eu, ev, iu, iv in lines:
            for along in ALONG_CELLS:
                # across the cell (perpendicular to inward), then from inside outwards
                base_u, base_v = eu + along * abs(iv), ev + along * abs(iu)
                t = -PROFILE_CELLS  # a negative offset is inside the white cell
                points.append(np.stack([base_u + t * iu, base_v + t * iv], axis=1))
                sides.append(side)
        if not points:
            return BorderProfiles(np.zeros((0, 2)), np.zeros(0, np.int64), n)
        return BorderProfiles(
            np.ascontiguousarray(np.concatenate(points)), np.array(sides, np.int64), n
        )


@dataclass(frozen=True)
class BorderWidths:
    """Each side's border width (4,: top, right, bottom, left) in cells of the fitted quad,
    and its standard error from the spread of the side's profiles; NaN for a side without
    profiles or one that could not be read."""

    cells: Array
    error: Array

    @staticmethod
    def unread() -> BorderWidths:
        return BorderWidths(np.full(4, np.nan), np.full(4, np.nan))


def border_widths(
    grey: NDArray[np.uint8], corners_px: Array, camera: CameraModel, profiles: BorderProfiles
) -> BorderWidths:
    """Each side's border width in cells of the quad ``corners_px`` (4, 2; ArUco order): where
    its profiles cross halfway between the white cell's level and the border's (the levels of
    the side's mean profile), their mean and its standard error."""
    if profiles.side.size == 0:
        return BorderWidths.unread()
    corners = np.ascontiguousarray(np.asarray(corners_px, np.float64).reshape(4, 2))
    cells, error = _widths_compiled(
        camera.compiled_lens,
        grey,
        corners,
        float(profiles.n_cells),
        profiles.points_uv,
        profiles.side,
        PROFILE_CELLS,
    )
    return BorderWidths(cells, error)


@compiled
def _widths_compiled(
    lens: Lens,
    grey: NDArray[np.uint8],
    corners_px: Array,
    n: float,
    points_uv: Array,
    side: NDArray[np.int64],
    offsets: Array,
) -> tuple[Array, Array]:
    """``border_widths`` through the lens of ``CameraModel.compiled_lens``."""
    cells, error = np.full(4, np.nan), np.full(4, np.nan)
    placed, px = cell_points_px(lens, corners_px, n, points_uv)
    if not placed:
        return cells, error
    values = bilinear_points(grey, px)
    S = offsets.shape[0]
    for k in range(4):
        mean = np.zeros(S)
        count = 0
        for p in range(side.shape[0]):
            row = values[p * S : (p + 1) * S]
            if side[p] == k and np.isfinite(row).all():
                mean += row
                count += 1
        if count < 2:
            continue
        bright, dark = _levels(mean / count, offsets)
        if not bright > dark:
            continue
        half = 0.5 * (bright + dark)
        total = total2 = 0.0
        crossed = 0
        for p in range(side.shape[0]):
            row = values[p * S : (p + 1) * S]
            if side[p] == k and np.isfinite(row).all():
                c = _crossing(row, offsets, half)
                if math.isfinite(c):
                    total += c
                    total2 += c * c
                    crossed += 1
        if crossed < 2:
            continue
        m = total / crossed
        var = max(0.0, total2 / crossed - m * m) * crossed / (crossed - 1)
        cells[k] = 1.0 - m
        error[k] = math.sqrt(var / crossed)
    return cells, error


@compiled
def _levels(profile: Array, offsets: Array) -> tuple[float, float]:
    """The mean of ``profile`` beyond ``LEVEL_BEYOND_CELLS`` on the white cell's side
    (negative ``offsets``) and on the border's."""
    bright = dark = 0.0
    n_bright = n_dark = 0
    for i in range(offsets.shape[0]):
        if offsets[i] < -LEVEL_BEYOND_CELLS:
            bright += profile[i]
            n_bright += 1
        elif offsets[i] > LEVEL_BEYOND_CELLS:
            dark += profile[i]
            n_dark += 1
    if n_bright == 0 or n_dark == 0:
        return math.nan, math.nan
    return bright / n_bright, dark / n_dark


@compiled
def _crossing(profile: Array, offsets: Array, half: float) -> float:
    """Where ``profile`` (bright at negative ``offsets``, dark at positive) first falls
    through ``half``, by linear interpolation (NaN: it never does)."""
    for i in range(1, offsets.shape[0]):
        if profile[i] < half <= profile[i - 1]:
            w = (profile[i - 1] - half) / (profile[i - 1] - profile[i])
            return float(offsets[i - 1] + w * (offsets[i] - offsets[i - 1]))
    return math.nan


@dataclass(frozen=True)
class OddBorder:
    """A side whose border reads wider than the others': which (0 top, 1 right, 2 bottom,
    3 left), its width and the others' median, in cells of the fitted quad."""

    side: int
    width_cells: float
    others_cells: float

    @property
    def excess_cells(self) -> float:
        return self.width_cells - self.others_cells

    def describe(self) -> str:
        return (
            f"{SIDE_NAMES[self.side]} edge moved in by {self.excess_cells:.2f} cells: its "
            f"border read {self.width_cells:.2f} cells wide against {self.others_cells:.2f} on "
            "the other sides (something dark along that edge?)"
        )


def odd_border(
    widths: BorderWidths,
    tolerance_cells: float = ODD_BORDER_CELLS,
    significance: float = ODD_BORDER_SIGMAS,
) -> OddBorder | None:
    """The side widest against the median of the others, where it is wider by more than
    ``tolerance_cells`` and than ``significance`` times the standard error of that difference
    (noise and compression spread a side's profiles); None where no side is (or fewer than
    three could be read)."""
    cells = [float(c) for c in widths.cells]
    error = [float(e) for e in widths.error]
    read = [k for k in range(4) if math.isfinite(cells[k]) and math.isfinite(error[k])]
    if len(read) < 3:
        return None
    found: OddBorder | None = None
    for k in read:
        others = [j for j in read if j != k]
        median = statistics.median(cells[j] for j in others)
        gap = cells[k] - median
        spread = math.hypot(error[k], statistics.median(error[j] for j in others))
        widest = 0.0 if found is None else found.excess_cells
        if gap > max(tolerance_cells, significance * spread, widest):
            found = OddBorder(k, cells[k], median)
    return found


# the corners each side runs between (ArUco order), and how moving it in changes the cell
# coordinates (u, v) of those corners
_SIDE_CORNERS = ((0, 1), (1, 2), (2, 3), (3, 0))
_SIDE_INWARD = ((0.0, 1.0), (-1.0, 0.0), (0.0, -1.0), (1.0, 0.0))


def moved_in(
    detection: MarkerDetection, camera: CameraModel, n_cells: int, odd: OddBorder
) -> MarkerDetection | None:
    """``detection`` with its odd side moved in by the excess width (through the fitted
    quad's own homography and the lens, so the side stays a straight line on the marker's
    plane), the two corners it moves given that move's length as further standard deviation
    (px) in their covariance; None where the quad makes no homography."""
    corners = np.ascontiguousarray(np.asarray(detection.corners_px, np.float64).reshape(4, 2))
    n = float(n_cells)
    moved = np.array([[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]])
    step = odd.excess_cells * np.array(_SIDE_INWARD[odd.side])
    for c in _SIDE_CORNERS[odd.side]:
        moved[c] += step
    placed, px = cell_points_px(camera.compiled_lens, corners, n, moved)
    if not (placed and np.isfinite(px).all()):
        return None
    covariance = detection.corner_covariance_px2
    if covariance is not None:
        covariance = np.array(covariance, np.float64, copy=True)
        for c in _SIDE_CORNERS[odd.side]:
            shift2 = float(np.sum((px[c] - corners[c]) ** 2))
            covariance[2 * c, 2 * c] += shift2
            covariance[2 * c + 1, 2 * c + 1] += shift2
    return replace(detection, corners_px=px, corner_covariance_px2=covariance)


def border_problem(
    grey: NDArray[np.uint8],
    detection: MarkerDetection,
    camera: CameraModel,
    profiles: BorderProfiles,
) -> OddBorder | None:
    """``odd_border`` of ``detection`` in ``grey``; None where its cells are under
    ``MIN_CELL_PX`` (too small to measure a border on)."""
    if detection.side_px / profiles.n_cells < MIN_CELL_PX:
        return None
    return odd_border(border_widths(grey, detection.corners_px, camera, profiles))
