"""Marker corners from the marker's four border edges, fitted through the lens model.

A corner found by gradient methods (OpenCV's SUBPIX, ``cornerSubPix``) sits a fraction of a
pixel inside the true corner of a blurred square: the blur rounds the corner and the gradient
structure there is no longer that of two straight edges. The edges themselves are not biased by
a symmetric blur: across an edge, the image is a step convolved with the blur, whose midpoint
is the edge. So each side of the marker's outer border is fitted, then the corners are the
intersections of neighbouring sides.

Per side, profiles run across the edge at points spaced along it. Each takes the pixels nearest
points spaced along the profile (each pixel once, weighted by how many points it is nearest),
at their centres' own offsets from the edge, and they are fitted
together with ``a + b * F(s - d_k)``, F a step blurred by a Gaussian of ``sigma`` and integrated
over the pixel's square: one edge offset ``d_k`` per profile, and dark level ``a``, contrast
``b`` and blur ``sigma`` shared by the marker (per side for large markers), by Gauss-Newton on
all of them at once. What the blur mixes in from around the edge
is modelled from the target's print: the border's inner edge where the cell inside is white,
and the end of the white margin outside (the sheet's edge, or another marker) when it lies
within a few pixels. The edge points are taken to the camera's normalised image plane, where a
straight edge of the printed square is a straight line for any lens model, and a line is fitted
to them (total least squares, outliers trimmed). Corners are intersected there and projected
back to pixels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.camera.lens import Lens, lens_normalize, lens_project
from perchpose.corners.edge_geometry import (
    corner_covariance,
    corner_probes,
    edge_points_n,
    fit_lines,
    intersect_sides,
    largest_move,
    lens_jacobians,
    outward_normals,
    sample_profiles,
    side_lengths,
    side_probes,
)
from perchpose.corners.step_model import (
    MAX_BLUR_PX,
    MIN_BLUR_PX,
    MIN_CONTRAST,
    fit_steps,
    profile_start,
)
from perchpose.numeric.jit import compiled

Array = NDArray[np.float64]
_SQRT2 = math.sqrt(2.0)


@dataclass(frozen=True)
class EdgeFitSettings:
    """inside_cells, outside_cells : how far the profiles reach across the edge into the black
    border (one cell wide, so well under 1) and into the white margin, in marker cells,
    measured from the start (``outside_reach_px``).
    min/max_window_px : bounds of those reaches.
    max_profiles : profiles per side (one per 2 px of side below that).
    trim : fraction of each side left out at both ends (the corners' neighbourhoods).
    max_shift_cells : a fitted corner further than this from its start is rejected (the start
    is kept).
    iterations : rounds of the step-model fit.
    own_levels_from_px : a marker whose sides are all at least this long fits dark and light
    levels per side, each changing linearly along its side, not one pair for the marker: across
    a large marker vignetting and lighting change them (analog renders of 160-400 px markers,
    webcam lens: 0.09 px RMS against 0.12 with a pair per side; fpv lens, 0.089 with a pair
    per side, 0.071 with the linear change); a small marker's few profiles fix one pair better.
    step_px : spacing of the points along a profile whose nearest pixels it fits, widened to
    keep at most max_samples per profile; under a pixel, every pixel across the edge is used
    (analog 160-400 px markers: 0.098 px RMS at the 1.2 px steps of 14 samples, 0.089 at 24)."""

    inside_cells: float = 0.45
    outside_cells: float = 0.7
    min_window_px: float = 1.0
    max_window_px: float = 8.0
    step_px: float = 0.35
    max_samples: int = 24
    max_profiles: int = 24
    trim: float = 0.1
    max_shift_cells: float = 0.6
    iterations: int = 4
    own_levels_from_px: float = 80.0

    def kernel(self) -> EdgeFitKernel:
        """The settings as compiled code takes them (``_plan``, ``_edges``)."""
        return EdgeFitKernel(
            float(self.inside_cells),
            float(self.outside_cells),
            float(self.min_window_px),
            float(self.max_window_px),
            float(self.step_px),
            float(self.max_samples),
            float(self.max_profiles),
            float(self.trim),
            float(self.iterations),
            float(self.own_levels_from_px),
        )


class EdgeFitKernel(NamedTuple):
    """``EdgeFitSettings`` as the compiled fit reads them: every one a float (the counts
    too, as the fit's arithmetic takes them)."""

    inside_cells: float
    outside_cells: float
    min_window_px: float
    max_window_px: float
    step_px: float
    max_samples: float
    max_profiles: float
    trim: float
    iterations: float
    own_levels_from_px: float


class SideFit(NamedTuple):
    """The four sides fitted (``_edges``): whether they were (``ok``), the corners in the
    normalised plane (4, 2), ``intersect_sides``' inverses (4, 2, 2), the lines' normals
    (4, 2) and centres (4, 2), their angle and shift variances (4,) each, and the blur sigma
    (px, with the pixel's own square in it)."""

    ok: bool
    corners_n: Array
    A_inv: Array
    normals: Array
    centres: Array
    angle_var: Array
    shift_var: Array
    blur_px: float


# a step further beyond the end of the profiles than this many blur sigmas (first guess) is
# left out of the model: its blur does not reach them, and its level could not be fitted
_BEYOND_REACH_SIGMAS = 3.0


@compiled
def _first_blur_px(rise: float, h: float, contrast: float) -> float:
    """A first guess of the optical blur sigma (px) from the profiles' mean steepest ``rise``
    between samples ``h`` px apart, for an edge of ``contrast``."""
    # for an edge midway between two samples h apart, the rise is b * erf(h / (2 sqrt(2) sigma))
    rise /= contrast
    sigma0 = _blur_from_rise(min(rise, 0.999), h) if rise > 0 else 1.0
    # that sigma holds the pixel's square (variance 1/12) and, from the interpolation, about
    # as much again
    sigma0 = math.sqrt(max(sigma0 * sigma0 - 1.0 / 6.0, MIN_BLUR_PX**2))
    return min(MAX_BLUR_PX, max(MIN_BLUR_PX, sigma0))


@compiled
def _surround_within(
    white: Array, border_px: Array, margin_px: Array, inner_reach: float, outer_reach: float
) -> tuple[Array, bool]:
    """``step_model.fit_steps``'s surround (3, K) of K profiles reaching ``inner_reach`` px
    inwards and ``outer_reach`` outwards (with the blur's own reach): ``white`` (1 where the
    cell just inside the border is white, the border's inner edge ``border_px`` inside the
    outer one then a second, reversed step) where that edge is within reach, else 0; the
    border's width; and where the white margin outside ends (``margin_px``: up to the sheet's
    edge or another marker, a third step to a level fitted with the rest) where within
    reach, else 1e6 px; and whether any margin's end is within reach."""
    K = white.shape[0]
    rows = np.empty((3, K))
    near_any = False
    for k in range(K):
        rows[0, k] = white[k] if border_px[k] < inner_reach else 0.0
        rows[1, k] = border_px[k]
        near = margin_px[k] < outer_reach
        rows[2, k] = margin_px[k] if near else 1e6
        near_any = near_any or near
    return rows, near_any


@compiled
def _level_design(sides: NDArray[np.intp], along: Array, own_levels: bool) -> Array:
    """The levels' design W (R, K) of K profiles: a profile's dark level is W[:, k] . a_q,
    its contrast W[:, k] . b_q. Without ``own_levels`` one pair for the marker (R = 1); with
    it one pair per side (``sides`` (K,): each profile's), each changing linearly with
    ``along`` (K,: the profile's place along its side, -1 to 1; vignetting and uneven light
    across a large marker)."""
    K = sides.shape[0]
    if not own_levels:
        return np.ones((1, K))
    n_groups = 0
    for k in range(K):
        n_groups = max(n_groups, int(sides[k]) + 1)
    W = np.zeros((2 * n_groups, K))
    for k in range(K):
        W[sides[k], k] = 1.0
        W[n_groups + sides[k], k] = along[k]
    return W


@compiled
def _fit_profiles(
    values: Array, offsets: Array, pixels: Array, W: Array, surround: Array, iterations: int
) -> tuple[bool, Array, float]:
    """The step model fitted to K profiles (K, M) sampled at ``offsets`` (M,), dark to light:
    (whether there is an edge, the edge offsets (K,), the optical blur sigma, px, without
    the pixel's own square). ``pixels`` (3, K, M): the data to fit, the offsets across the
    edge of the pixels nearest the samples, their values and how many samples each stands
    for (0 for a repeat; ``sample_profiles``); the samples themselves give the starting
    values only. ``W``: the levels' design (``_level_design``). ``surround`` (3, K): the
    white inside the border, its width and the white margin's end (px), for
    ``_surround_within``.

    Model: ``a + b * F(s - d_k)``, F a step blurred by ``sigma`` and integrated over the pixel
    (``step_model.pixel_step``), fitted to the pixels themselves at their exact offsets. A
    Gaussian step fitted to bilinearly interpolated samples instead locks the edge to the pixel
    grid by an amount that depends on where the edge falls in a pixel: on a 25 px marker turned
    0.5-2 deg from the pixel rows (noise-free), up to 0.19 deg of yaw at an optical blur of
    0.3 px and 0.016 deg at 0.6 px. The surround enters the model where it is within reach of
    the profiles: blur mixes both into the profiles once they are within a few sigma, and left
    out they pull the edge (by 0.1 px for a 30 px marker whose margin is under a cell, at a
    blur of 1.1 px). Gauss-Newton from the midpoint crossings on all parameters at once
    (``step_model.fit_steps``)."""
    lo, hi, d, rise = profile_start(values, offsets)
    if not hi - lo > MIN_CONTRAST:
        return False, d, 0.0
    # each group's dark level and contrast to start from; their slopes along the side at 0
    levels = np.zeros((2, W.shape[0]))
    n_groups = W.shape[0] if W.shape[0] == 1 else W.shape[0] // 2
    for q in range(n_groups):
        levels[0, q] = lo
        levels[1, q] = hi - lo
    log_sigma = math.log(_first_blur_px(rise, offsets[1] - offsets[0], hi - lo))
    beyond = _BEYOND_REACH_SIGMAS * math.exp(log_sigma) + 0.5
    around, with_margin = _surround_within(
        surround[0], surround[1], surround[2], -offsets[0] + beyond, offsets[-1] + beyond
    )
    ok, log_sigma = fit_steps(pixels, d, W, levels, log_sigma, around, with_margin, iterations)
    return ok, d, math.exp(log_sigma)


@compiled
def _blur_from_rise(rise: float, h: float) -> float:
    """The sigma at which a unit blurred step rises by ``rise`` across ``h`` centred on it."""
    sigma = h / 2.0
    for _ in range(8):  # Newton on erf(h / (2 sqrt(2) sigma)) = rise
        x = h / (2.0 * _SQRT2 * sigma)
        f = math.erf(x) - rise
        df = -2.0 / math.sqrt(math.pi) * math.exp(-x * x) * x / sigma
        if df == 0.0:
            break
        sigma = min(6.0, max(0.2, sigma - f / df))
    return sigma


@compiled
def _inner_cells_white(cells: NDArray[np.uint8], t: Array) -> Array:
    """(4K,): whether the cell just inside the border is white at fractions ``t`` (K,) along
    each side, sides one after the other in ArUco corner order (top left to right, right
    downwards, bottom right to left, left upwards; ``cells`` row 0 is the top)."""
    n = cells.shape[0]
    K = t.shape[0]
    white = np.empty(4 * K)
    for k in range(K):
        j = min(max(int(math.floor(t[k] * n)), 0), n - 1)
        back = n - 1 - j
        white[k] = cells[1, j]
        white[K + k] = cells[j, n - 2]
        white[2 * K + k] = cells[n - 2, back]
        white[3 * K + k] = cells[back, 1]
    return white


@dataclass(frozen=True)
class EdgeFit:
    """A marker's corners (4, 2) from its fitted border edges, the blur sigma the fit found
    (pixels; with the pixels' own area in it), and the corners' covariance (8, 8; px^2,
    x0, y0, x1, ...) from the edge points' scatter about the fitted sides."""

    corners_px: Array
    blur_px: float
    covariance_px2: Array


_STEP_N = 1e-6  # normalised-plane step of the lens model's numerical Jacobian


def outside_reach_px(cell_px: float, settings: EdgeFitSettings | None = None) -> float:
    """How far (px) the profiles reach outwards from the start of a marker with cells of
    ``cell_px``."""
    cfg = settings or EdgeFitSettings()
    return min(cfg.max_window_px, max(cfg.min_window_px, cfg.outside_cells * cell_px))


@compiled
def _plan(
    corners: Array, n_cells: int, cfg: EdgeFitKernel
) -> tuple[Array, Array, Array, float, float]:
    """Where a marker's profiles go, from its start ``corners`` (4, 2) and the settings
    ``cfg``: the sides' lengths (4,), the offsets (M,) along each profile (px, from
    ``-reach_in`` towards ``reach_out``), the fractions (K,) of each side the profiles cross,
    the width of a cell and ``reach_out`` (px)."""
    inside, outside = cfg.inside_cells, cfg.outside_cells
    min_window, max_window = cfg.min_window_px, cfg.max_window_px
    step_px, max_samples, max_profiles, trim = (
        cfg.step_px,
        cfg.max_samples,
        cfg.max_profiles,
        cfg.trim,
    )
    sides_px = side_lengths(corners)
    cell_px = 0.25 * (sides_px[0] + sides_px[1] + sides_px[2] + sides_px[3]) / n_cells
    reach_in = min(max_window, max(min_window, inside * cell_px))
    reach_out = min(max_window, max(min_window, outside * cell_px))
    step = max(step_px, (reach_in + reach_out) / (max_samples - 1.0))
    offsets = np.arange(-reach_in, reach_out + 1e-9, step)
    K = int(min(max_profiles, max(4.0, sides_px.min() / 2.0)))
    t = np.empty(K)  # evenly from trim to 1 - trim, as numpy's linspace places them
    spacing = (1.0 - 2.0 * trim) / (K - 1)
    for k in range(K):
        t[k] = k * spacing + trim
    t[K - 1] = 1.0 - trim
    return sides_px, offsets, t, cell_px, reach_out


@compiled
def _edges(
    grey: NDArray[np.uint8],
    corners: Array,
    plan: tuple[Array, Array, Array, float, float],
    probed: tuple[Array, Array, Array, Array],
    printed: tuple[Array, Array, int],
    cfg: EdgeFitKernel,
) -> SideFit:
    """The four sides of the marker whose start is ``corners`` fitted through the profiles
    across them: ``plan`` from ``_plan``; ``probed``, the side points in the normalised
    plane, their steps along and across, and the pixels (12K, 2) the lens puts them at
    (``side_probes``, projected); ``printed``: where the cell inside the border is white
    (4K,: 1 there), how far the white around the marker reaches (4,: in cells, per side)
    and the cells across."""
    sides_px, offsets, t, _, reach_out = plan
    white, margins, n_cells = printed
    p_n, step_n, perp_n, projected = probed
    K = t.shape[0]
    n = 4 * K
    empty2, empty3 = np.zeros((4, 2)), np.zeros((4, 2, 2))
    nothing = SideFit(False, empty2, empty3, empty2, empty2, np.zeros(4), np.zeros(4), 0.0)
    centre_x = 0.25 * (corners[0, 0] + corners[1, 0] + corners[2, 0] + corners[3, 0])
    centre_y = 0.25 * (corners[0, 1] + corners[1, 1] + corners[2, 1] + corners[3, 1])
    normal = outward_normals(projected, centre_x, centre_y)
    # bilinear samples to start from; the fit's data: the pixel nearest each sample, at its
    # own offset across the edge
    values, pixels, rows = sample_profiles(grey, projected[:n], normal, offsets)
    kept = np.nonzero(rows)[0]
    if kept.shape[0] < 12:
        return nothing
    own_levels = sides_px.min() >= cfg.own_levels_from_px
    surround = np.empty((3, kept.shape[0]))
    sides = np.empty(kept.shape[0], np.intp)
    along = np.empty(kept.shape[0])
    for j in range(kept.shape[0]):
        i = kept[j]
        s = i // K
        # a cell's width across side s: the perpendicular sides' lengths over n
        across = (sides_px[(s + 3) % 4] + sides_px[(s + 1) % 4]) / (2.0 * n_cells)
        surround[0, j] = white[i]
        surround[1, j] = across
        surround[2, j] = margins[s] * across
        sides[j] = s
        along[j] = 2.0 * t[i % K] - 1.0
    W = _level_design(sides, along, own_levels)
    fitted, d_kept, optical_blur_px = _fit_profiles(
        values[kept], offsets, pixels[:, kept], W, surround, int(cfg.iterations)
    )
    if not fitted:
        return nothing
    d = np.full(n, np.nan)
    good = np.zeros(n, np.bool_)
    for j in range(kept.shape[0]):
        d[kept[j]] = d_kept[j]
    reach_in = -offsets[0]
    for i in range(n):
        good[i] = math.isfinite(d[i]) and d[i] > -reach_in and d[i] < reach_out
    edge_n = edge_points_n(p_n, step_n, perp_n, projected, normal, d)
    lined, normals, line_offsets, centres, angle_var, shift_var = fit_lines(
        edge_n.reshape(4, K, 2), good.reshape(4, K)
    )
    if not lined:
        return nothing
    met, corners_n, A_inv = intersect_sides(normals, line_offsets)
    if not met:
        return nothing
    blur_px = math.sqrt(optical_blur_px**2 + 1.0 / 12.0)
    return SideFit(True, corners_n, A_inv, normals, centres, angle_var, shift_var, blur_px)


@compiled
def _covariance_and_move(
    projected: Array,
    fitted: SideFit,
    corners: Array,
) -> tuple[Array, Array, float]:
    """From the pixels (12, 2) of the fitted corners' ``corner_probes`` and the sides'
    fit (``_edges``): the corners (4, 2) and their covariance (8, 8; px^2), from the lines'
    own (the lens's Jacobian at each corner by forward differences), and how far the
    farthest corner moved from ``corners`` (px)."""
    corners_px, lens = lens_jacobians(projected, _STEP_N)
    covariance = corner_covariance(
        lens,
        fitted.A_inv,
        fitted.corners_n,
        fitted.normals,
        fitted.centres,
        fitted.angle_var,
        fitted.shift_var,
    )
    return corners_px, covariance, largest_move(corners_px, corners)


@compiled
def _edge_fit_compiled(
    grey: NDArray[np.uint8],
    corners: Array,
    lens: Lens,
    cells: NDArray[np.uint8],
    n_cells: int,
    margins: Array,
    cfg: EdgeFitKernel,
) -> tuple[bool, Array, Array, float, float]:
    """``fit_marker_edges`` through the lens of ``CameraModel.compiled_lens``: (whether the
    sides were fitted, the corners (4, 2) and their covariance (8, 8), the blur sigma, how
    far the farthest corner moved, px). ``cells``: the marker's cells, or an empty (0, 0)
    array for the outer edge alone; ``n_cells`` across."""
    kind, K_px, coefficients = lens
    failed = (False, corners, np.zeros((8, 8)), 0.0, 0.0)
    plan = _plan(corners, n_cells, cfg)
    t = plan[2]
    xy = lens_normalize(kind, corners, K_px, coefficients)
    for i in range(4):
        if not (math.isfinite(xy[i, 0]) and math.isfinite(xy[i, 1])):
            return failed
    p_n, step_n, perp_n, probes = side_probes(xy, t)
    projected, ok = lens_project(kind, probes, K_px, coefficients)
    if not ok.all():
        return failed
    white = _inner_cells_white(cells, t) if cells.shape[0] > 0 else np.zeros(4 * t.shape[0])
    probed = (p_n, step_n, perp_n, projected)
    fitted = _edges(grey, corners, plan, probed, (white, margins, n_cells), cfg)
    if not fitted.ok:
        return failed
    at_corners, ok = lens_project(
        kind, corner_probes(fitted.corners_n, _STEP_N), K_px, coefficients
    )
    if not ok.all():
        return failed
    corners_px, covariance, moved = _covariance_and_move(at_corners, fitted, corners)
    return True, corners_px, covariance, fitted.blur_px, moved


_NO_CELLS = np.zeros((0, 0), np.uint8)


def fit_marker_edges(
    grey: NDArray[np.uint8],
    corners_px: Array,
    camera: CameraModel,
    cells: int | NDArray[np.uint8],
    settings: EdgeFitSettings | None = None,
    margin_cells: Sequence[float] | None = None,
) -> EdgeFit | None:
    """A marker's corners from its four fitted border edges, or None if a side cannot be
    fitted or a corner would move too far from ``corners_px`` (a good start, e.g. from
    ``cornerSubPix``). ``cells``: the marker's cells (``MarkerSpec.cells``, border included),
    whose white cells next to the border enter the edge model; or just how many there are
    across, to fit the outer edge alone. ``margin_cells``: per side (ArUco order), how far the
    white around the marker reaches, in its cells (``TargetSpec.white_margin_cells``); where
    that is within reach of the profiles its end enters the model too. Runs compiled whole
    (``_edge_fit_compiled``)."""
    cfg = settings or EdgeFitSettings()
    corners = np.ascontiguousarray(corners_px, np.float64).reshape(4, 2)
    if isinstance(cells, int):
        printed, n_cells = _NO_CELLS, cells
    else:
        printed, n_cells = np.ascontiguousarray(cells, np.uint8), int(cells.shape[0])
    margins = np.full(4, np.inf) if margin_cells is None else np.asarray(margin_cells, float)
    lens = camera.compiled_lens
    fitted = _edge_fit_compiled(grey, corners, lens, printed, n_cells, margins, cfg.kernel())
    ok, refined, covariance, blur_px, moved = fitted
    cell_px = 0.25 * float(side_lengths(corners).sum()) / n_cells
    if not ok or moved > cfg.max_shift_cells * cell_px:
        return None
    return EdgeFit(refined, blur_px, covariance)
