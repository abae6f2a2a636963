"""Corners of a small marker from a fit of its whole printed pattern to the image.

Where a marker's cells are only a few blur widths across, what the blur mixes into its border
edges comes from every side: the neighbouring side near a corner, the inner cells, the margin
around it. A model of one edge at a time then pulls the corners inwards (0.14 px at 15-20 px
sides with a blur of 1.1 px). So for such markers the image around the marker is fitted as a
whole: the printed pattern (the marker's cells and whatever else is printed within reach,
taken from the target) seen through a homography from the camera's normalised image plane,
blurred by a Gaussian of one width in pixels, with dark, light and off-sheet grey levels.

The pattern's edges are axis-aligned in the marker's own cell coordinates (u, v), so the
blurred pattern is separable there: for a pixel at (u, v), each cell's blurred coverage is the
product of two differences of normal CDFs, with the pixel blur taken to (u, v) through the
local Jacobian of the pixel-to-marker map (the lens model's and the homography's). Straight
edges of the blurred model are exact for any lens; at the corners the small correlation a
tilted view brings between u and v is left out. Gauss-Newton on the homography's 8 entries,
the blur and the grey levels at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.corners.edge_geometry import largest_move, side_lengths
from perchpose.corners.pattern_model import REACH_SIGMAS, fit_pattern
from perchpose.corners.step_model import MIN_CONTRAST
from perchpose.numeric.linalg import homography_of_4
from perchpose.target import TargetSpec
from perchpose.values import quad_side_px

Array = NDArray[np.float64]

# pattern lines further than this from the marker (in its cells) are merged into one band: a
# blur that reaches further would hide the marker's own cells
_PATTERN_REACH_CELLS = 5.0
_FAR = 1e4  # the outermost bands reach this far (cells)
# cell codes
_OFF_SHEET, _BLACK, _WHITE = -1, 0, 1


@dataclass(frozen=True)
class PrintedPattern:
    """What is printed around one marker of a target, in that marker's cell coordinates.

    u runs from the marker's corner 0 towards corner 1, v from corner 0 towards corner 3; the
    marker covers [0, n_cells] in both. lines_u (Nu + 1,), lines_v (Nv + 1,) : the edges of a
    grid of bands, the outermost reaching far beyond; code (Nv, Nu) : each grid cell's print
    (1 white, 0 black, -1 off the sheet). sheet_cells : per side (ArUco order: top, right,
    bottom, left) how far the sheet reaches beyond the marker, in its cells (inf: no edge
    within reach). fine : the boxes (u0, u1, v0, v1) of markers printed within this one with
    smaller cells.
    """

    n_cells: int
    lines_u: Array
    lines_v: Array
    code: NDArray[np.int8]
    sheet_cells: tuple[float, float, float, float]
    fine: tuple[tuple[float, float, float, float], ...] = ()


def printed_pattern(target: TargetSpec, index: int) -> PrintedPattern | None:
    """Marker ``index``'s printed surroundings on a grid of its own cells, or None if another
    marker within reach is printed at an angle to it (the grid would not be separable)."""
    marker = target.markers[index]
    n = int(marker.cells.shape[0])
    c0, c1, _, c3 = marker.corners_target_m[:, :2]
    cell_m = marker.side_m / n
    e_u = (c1 - c0) / np.linalg.norm(c1 - c0)
    e_v = (c3 - c0) / np.linalg.norm(c3 - c0)

    def to_cells(p: Array) -> Array:
        d = np.asarray(p, np.float64) - c0
        return np.stack([d @ e_u, d @ e_v], axis=-1) / cell_m

    lines_u: list[float] = [0.0, float(n)]
    lines_v: list[float] = [0.0, float(n)]
    lo, hi = -_PATTERN_REACH_CELLS, n + _PATTERN_REACH_CELLS
    fine: list[tuple[float, float, float, float]] = []
    for other in target.markers:
        uv = to_cells(other.corners_target_m[:, :2])
        n_other = int(other.cells.shape[0])
        us, vs = np.unique(np.round(uv[:, 0], 9)), np.unique(np.round(uv[:, 1], 9))
        if not (np.all(uv.max(axis=0) >= lo) and np.all(uv.min(axis=0) <= hi)):
            continue  # out of reach
        if us.size != 2 or vs.size != 2:
            return None
        lines_u.extend(np.linspace(us[0], us[1], n_other + 1).tolist())
        lines_v.extend(np.linspace(vs[0], vs[1], n_other + 1).tolist())
        inside = us[0] >= 0 and vs[0] >= 0 and us[1] <= n and vs[1] <= n
        if inside and other.side_m / n_other < cell_m:
            fine.append((float(us[0]), float(us[1]), float(vs[0]), float(vs[1])))
    half = target.sheet_half_extent_m
    sheet = to_cells(np.array([[-half, -half], [half, half]]))
    sheet_u, sheet_v = np.sort(sheet[:, 0]), np.sort(sheet[:, 1])
    lines_u.extend(sheet_u.tolist())
    lines_v.extend(sheet_v.tolist())

    def grid(lines: list[float]) -> Array:
        kept = np.unique(np.round(np.asarray(lines), 9))
        kept = kept[(kept > lo) & (kept < hi)]
        return np.concatenate([[-_FAR], kept, [_FAR]])

    gu, gv = grid(lines_u), grid(lines_v)
    mid_u = np.clip(0.5 * (gu[:-1] + gu[1:]), gu[1] - 0.25, gu[-2] + 0.25)
    mid_v = np.clip(0.5 * (gv[:-1] + gv[1:]), gv[1] - 0.25, gv[-2] + 0.25)
    mu, mv = np.meshgrid(mid_u * cell_m, mid_v * cell_m)
    xy = c0 + mu[..., None] * e_u + mv[..., None] * e_v
    albedo = target.albedo(xy[..., 0], xy[..., 1])
    code = np.where(np.isnan(albedo), _OFF_SHEET, np.where(albedo > 0.5, _WHITE, _BLACK))
    sheet_cells = (-sheet_v[0], sheet_u[1] - n, sheet_v[1] - n, -sheet_u[0])
    far = [math.inf if s > _PATTERN_REACH_CELLS else float(s) for s in sheet_cells]
    reach = (far[0], far[1], far[2], far[3])
    return PrintedPattern(n, gu, gv, code.astype(np.int8), reach, tuple(fine))


@dataclass(frozen=True)
class PatternFitSettings:
    """Which markers get the pattern fit: every marker up to all_below_px, and up to
    max_side_px those whose cells span fewer than below_cell_blurs blur sigmas (the edge
    fit's blur: its corners are then pulled inwards, -0.03 px at 4 sigmas, -0.14 px at 2.3)
    or whose edge fit failed. Below all_below_px the choice does not hang on the blur measured
    in each frame: switching methods from frame to frame would add their difference to the
    noise. The fit's cost grows with the marker's area and its blur: on harsh frames (blur
    about 1.8 px, 2x2 blocks) about 1-3 ms at 30-57 px on a 2-core x86 machine.

    out_cells : how far beyond the marker's border the fitted pixels reach, in its cells
    (never past 90 % of the way to the sheet's edge). iterations : Gauss-Newton rounds at most.
    max_shift_cells : a corner further than this from its start fails the fit;
    max_shift_quad_cells : the same from a start that is a found quad's corners, not fitted
    ones (``cornerSubPix`` on a harsh frame: up to 0.7 of a cell off at 30 px, where the fit
    from there lands within 0.15 px of the true corners). min_blur_px,
    max_blur_px : the blur's bounds; a fit that ends on one fails. min_contrast : grey levels
    between the print's black and white under which there is no pattern to fit (the edge fit's
    own threshold). bin_above_blur_px : from this blur (the edge fit's) the fit runs on 2x2
    blocks of pixels (their mean grey at their centre; the fitted blur takes in the block's
    width): a blur this wide leaves little detail at the scale of a pixel (harsh frames,
    30-57 px: corners 0.275 px RMS from the truth against 0.273 on pixels).

    Bands: analog interference (hum bars) and a rolling shutter under flickering light add a
    grey that changes from row to row. The fit can take it in as cosines over the fitted rows
    (``pattern_model.normal_equations``) down to a period of band_period_px. That costs
    precision where there are none (10-25 % more corner noise on `analog_fpv` frames), so the
    fit first runs without them and goes on with them only where its residuals show them
    (``pattern_model.banded``): where the cosines would take away over banded_above times the
    squared residuals they would by chance (a score test), and over twice what cosines over
    the columns would (shading, JPEG blocks and the model's own misfit show both ways). On the
    evaluation's fpv approach, `analog_fpv` frames (no interference, about 240 fits over three
    seeds) score a median of 1-2 along the rows and at most 7.4; harsh frames with
    interference a median of 33-35, with 10 % under 9-12. Interference belongs to the video
    link, not to one frame, and one frame's test can miss weaker bands that still pull the
    corners: once a fit finds them over banded_fits_above, the next banded_fits pattern fits
    (``CornerFitter``) take the bands in from their first round; a fit that finds them only
    over banded_above takes them in alone (an analog frame now and then does).
    """

    all_below_px: float = 24.0
    below_cell_blurs: float = 5.0
    max_side_px: float = 64.0
    out_cells: float = 0.7
    iterations: int = 12
    max_shift_cells: float = 0.6
    max_shift_quad_cells: float = 1.0
    min_blur_px: float = 0.15
    max_blur_px: float = 6.0
    min_contrast: float = MIN_CONTRAST
    bin_above_blur_px: float = 1.5
    band_period_px: float = 16.0
    banded_above: float = 4.0
    banded_fits: int = 30
    banded_fits_above: float = 12.0

    def applies(self, side_px: float, n_cells: int, blur_px: float | None) -> bool:
        """Whether a marker of ``side_px`` and ``n_cells`` across gets the pattern fit, given
        the edge fit's blur (None: the edge fit failed)."""
        if side_px > self.max_side_px:
            return False
        if side_px <= self.all_below_px or blur_px is None:
            return True
        return side_px / n_cells < self.below_cell_blurs * blur_px


def _inverse(g: Array) -> Array | None:
    """The 8 entries (h33 = 1) of the inverse of homography ``g``, or None if it has none."""
    try:
        h = np.linalg.inv(np.append(g, 1.0).reshape(3, 3))
    except np.linalg.LinAlgError:
        return None
    if h[2, 2] == 0:
        return None
    return np.asarray((h / h[2, 2]).ravel()[:8], np.float64)


def _apply(g: Array, q: Array) -> tuple[Array, Array, Array]:
    """(u, v) of points ``q`` (P, 2) under homography entries ``g``, and the denominator."""
    w = g[6] * q[:, 0] + g[7] * q[:, 1] + 1.0
    u = (g[0] * q[:, 0] + g[1] * q[:, 1] + g[2]) / w
    v = (g[3] * q[:, 0] + g[4] * q[:, 1] + g[5]) / w
    return u, v, w


@dataclass(frozen=True)
class _MarkerPlane:
    """The marker's frame in the normalised image plane: ``q = (xy - centre) / scale``."""

    camera: CameraModel
    centre: Array
    scale: float

    def q_of(self, px: Array) -> Array:
        q: Array = (self.camera.normalize(px) - self.centre) / self.scale
        return q

    def to_pixels(self, homography: Array, uv: Array) -> tuple[Array, NDArray[np.bool_]]:
        """Pixels of marker points ``uv`` (cells) under q -> (u, v) ``homography``."""
        inverse = _inverse(homography)
        if inverse is None:
            return np.full((len(uv), 2), np.nan), np.zeros(len(uv), bool)
        qx, qy, _ = _apply(inverse, uv)
        plane = np.stack(
            [qx * self.scale + self.centre[0], qy * self.scale + self.centre[1], np.ones_like(qx)],
            1,
        )
        return self.camera.project(plane)

    def blur_jacobian(self, mid_px: Array) -> tuple[tuple[float, float], tuple[float, float]]:
        """d(qx, qy)/d(pixel x) and d(qx, qy)/d(pixel y) at ``mid_px``: the lens model's
        pixel-to-q Jacobian, taken at the marker's centre (it changes by well under 1 % across
        a marker this small, and only scales the blur)."""
        ends = self.camera.normalize(np.array([mid_px, mid_px + [0.5, 0.0], mid_px + [0.0, 0.5]]))
        d_x = (ends[1] - ends[0]) * (2.0 / self.scale)
        d_y = (ends[2] - ends[0]) * (2.0 / self.scale)
        return (float(d_x[0]), float(d_x[1])), (float(d_y[0]), float(d_y[1]))


def _fitted_pixels(
    grey: NDArray[np.uint8],
    plane: _MarkerPlane,
    g: Array,
    pattern: PrintedPattern,
    out_cells: float,
    bin_px: int = 1,
    fine_margin_cells: float = 0.0,
) -> tuple[Array, Array, Array, NDArray[np.int64]] | None:
    """The pixels fitted (P, 2), their marker-plane points q (P, 2) and grey values (P,):
    those whose centres fall within ``out_cells`` of the marker (and on the sheet), from a box
    around the region's outline; None when too few. With ``bin_px`` over 1, blocks of that
    many pixels square stand for their pixels: the block's centre and mean grey. Pixels
    within ``fine_margin_cells`` of a finer marker printed inside (``pattern.fine``) along
    both axes are left out: blurred, its cells are a grey that says little of this marker's
    corners, where the model (one Gaussian blur) is least true, and a pixel seeing its lines
    both ways costs the most to model."""
    n = pattern.n_cells
    out = np.array([min(out_cells, 0.9 * s) for s in pattern.sheet_cells])  # top right ...
    lo_u, hi_u, lo_v, hi_v = -out[3], n + out[1], -out[0], n + out[2]
    outline_uv = np.array(
        [[lo_u, lo_v], [hi_u, lo_v], [hi_u, hi_v], [lo_u, hi_v]]
        + [[(lo_u + hi_u) / 2, lo_v], [hi_u, (lo_v + hi_v) / 2]]
        + [[(lo_u + hi_u) / 2, hi_v], [lo_u, (lo_v + hi_v) / 2]]
    )
    outline_px, ok = plane.to_pixels(g, outline_uv)
    if not ok.all():
        return None
    h_img, w_img = grey.shape[:2]
    x0 = max(0, int(math.floor(outline_px[:, 0].min())) - 1)
    y0 = max(0, int(math.floor(outline_px[:, 1].min())) - 1)
    x1 = min(w_img - 1, int(math.ceil(outline_px[:, 0].max())) + 1)
    y1 = min(h_img - 1, int(math.ceil(outline_px[:, 1].max())) + 1)
    # whole blocks only
    nx, ny = (x1 - x0 + 1) // bin_px, (y1 - y0 + 1) // bin_px
    if nx < 2 or ny < 2:
        return None
    box = grey[y0 : y0 + ny * bin_px, x0 : x0 + nx * bin_px].astype(np.float64)
    blocks = box.reshape(ny, bin_px, nx, bin_px).mean(axis=(1, 3))
    centre = 0.5 * (bin_px - 1)
    gx, gy = np.meshgrid(
        x0 + centre + bin_px * np.arange(nx, dtype=np.float64),
        y0 + centre + bin_px * np.arange(ny, dtype=np.float64),
    )
    px = np.stack([gx.ravel(), gy.ravel()], axis=1)
    q = plane.q_of(px)
    u, v, _ = _apply(g, q)
    inside = np.isfinite(u) & (u > lo_u) & (u < hi_u) & (v > lo_v) & (v < hi_v)
    m = fine_margin_cells
    for u0, u1, v0, v1 in pattern.fine:
        inside &= ~((u > u0 - m) & (u < u1 + m) & (v > v0 - m) & (v < v1 + m))
    if np.count_nonzero(inside) * bin_px * bin_px < 4 * n * n:
        return None
    rows, cols = np.divmod(np.arange(ny * nx, dtype=np.int64)[inside], nx)
    pixel_of = np.stack([rows - rows.min(), cols - cols.min()], axis=1)
    return px[inside], q[inside], blocks.ravel()[inside], pixel_of


def _start(corners: Array, camera: CameraModel, n: int) -> tuple[_MarkerPlane, Array] | None:
    """The marker's plane and the homography from it to the cells square, from the corners;
    None where they do not give one."""
    xy = camera.normalize(corners)
    if not np.isfinite(xy).all():
        return None
    scale = 0.25 * float(side_lengths(np.ascontiguousarray(xy)).sum()) / n
    if not scale > 0:
        return None
    centre = xy.mean(axis=0)
    found, H = homography_of_4(np.ascontiguousarray((xy - centre) / scale), _square(n))
    if not found:
        return None
    g = H.ravel()[:8].copy()
    return _MarkerPlane(camera, centre, scale), g


def _square(n: int) -> Array:
    return np.array([[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]])


@dataclass(frozen=True)
class PatternFit:
    """What a pattern fit found: the corners (4, 2) and how banded its residuals were by row
    (the score test of ``PatternFitSettings``, at its last round; NaN where it could not
    tell)."""

    corners_px: Array
    banding: tuple[float, float]


def refine_corners_pattern(
    grey: NDArray[np.uint8],
    corners_px: Array,
    camera: CameraModel,
    pattern: PrintedPattern,
    settings: PatternFitSettings | None = None,
    blur_px: float = 1.0,
    *,
    from_quad: bool = False,
    banded: bool = False,
) -> PatternFit | None:
    """Corners (4, 2) of a marker from a fit of its printed pattern (``printed_pattern``) to
    the pixels around it, and how banded the residuals were by row; or None if the fit fails
    or a corner would move too far from ``corners_px`` (a good start: e.g. the edge fit's
    corners). ``blur_px``: a first guess of the blur sigma (e.g. the edge fit's).
    ``from_quad``: the start is a found quad's corners, not fitted ones (a corner may move
    further: ``max_shift_quad_cells``). ``banded``: the video is known to be banded (the
    band model from the first round)."""
    cfg = settings or PatternFitSettings()
    corners = np.asarray(corners_px, np.float64).reshape(4, 2)
    n = pattern.n_cells
    cell_px = quad_side_px(corners) / n
    started = _start(corners, camera, n)
    bin_px = 2 if blur_px >= cfg.bin_above_blur_px else 1
    # a pixel's blur reaches this far (cells): further from a finer marker, it does not see it
    reach_cells = REACH_SIGMAS * blur_px / cell_px
    region = None
    if started is not None:
        region = _fitted_pixels(grey, *started, pattern, cfg.out_cells, bin_px, reach_cells)
    if started is None or region is None:
        return None
    plane, g = started
    _, q, values, pixel_of = region
    q_per_px = np.asarray(plane.blur_jacobian(corners.mean(axis=0)), np.float64)
    code = pattern.code
    off = (code == _OFF_SHEET).astype(np.float64)
    basis = np.stack([(code != _OFF_SHEET), (code == _WHITE)] + ([off] if off.any() else []))
    basis = np.ascontiguousarray(basis, np.float64)
    dark, light = float(np.percentile(values, 10)), float(np.percentile(values, 90))
    levels = np.array([dark, light - dark, dark][: len(basis)])
    log_sigma = math.log(min(cfg.max_blur_px, max(cfg.min_blur_px, blur_px)))
    # how far a unit change of each homography entry moves a corner of the cells square
    reach = np.array([n, n, 1.0, n, n, 1.0, n * n, n * n])
    # a step under 0.01 px ends it: the next one would move the corners by about a tenth of
    # that (on 78 harsh fits, at most 0.001 px against going on to 0.003 px)
    # the cosines over the rows down to a period of band_period_px
    n_rows = int(pixel_of[:, 0].max()) + 1
    n_row_bands = int(2 * n_rows * bin_px / cfg.band_period_px)
    solved, g, log_sigma, levels, banding = fit_pattern(
        np.ascontiguousarray(q),
        values,
        q_per_px,
        (pattern.lines_u, pattern.lines_v, basis),
        (g, log_sigma, levels),
        (cfg.iterations, reach, 1e-2 / cell_px),
        (pixel_of, n_row_bands, 0.0 if banded else cfg.banded_above),
    )
    if not solved:
        return None
    sigma = math.exp(log_sigma)
    if not (cfg.min_blur_px < sigma < cfg.max_blur_px) or not levels[1] > cfg.min_contrast:
        return None
    refined, ok = plane.to_pixels(g, _square(n))
    if not ok.all() or not np.isfinite(refined).all():
        return None
    max_shift_cells = cfg.max_shift_quad_cells if from_quad else cfg.max_shift_cells
    if largest_move(refined, corners) > max_shift_cells * cell_px:
        return None
    return PatternFit(np.asarray(refined, np.float64), banding)
