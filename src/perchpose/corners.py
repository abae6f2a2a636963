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

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.edge_geometry import (
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
from perchpose.jit import compiled
from perchpose.step_model import (
    MAX_BLUR_PX,
    MIN_BLUR_PX,
    MIN_CONTRAST,
    fit_steps,
    profile_start,
)

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


@dataclass(frozen=True)
class _Surround:
    """What lies around the edge of each of K profiles, in pixels across the edge.

    white_inside : 1 where the cell just inside the border is white (the border's inner edge,
        ``border_px`` inside the outer one, is then a second, reversed step), else 0.
    margin_px : width of the white outside the border, up to where the print or the sheet
        ends (a third step, to a level fitted with the rest), or inf where it reaches beyond
        the profiles.
    """

    white_inside: Array
    border_px: Array
    margin_px: Array


# a step further beyond the end of the profiles than this many blur sigmas (first guess) is
# left out of the model: its blur does not reach them, and its level could not be fitted
_BEYOND_REACH_SIGMAS = 3.0


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


def _surround_rows(
    surround: _Surround | None, offsets: Array, sigma_px: float, n_profiles: int
) -> tuple[Array, bool]:
    """``step_model.fit_steps``'s surround (3, K): 1 where the cell inside the border is white
    and its inner edge within reach of the blur of ``sigma_px`` from the profiles' ends at
    ``offsets`` (else 0), how far inside that edge lies, and where the white margin outside
    ends (1e6 px where out of reach); and whether any margin's end is within reach."""
    if surround is None:
        rows = np.zeros((3, n_profiles))
        rows[2] = 1e6
        return rows, False
    beyond = _BEYOND_REACH_SIGMAS * sigma_px + 0.5
    return _surround_within(
        surround.white_inside,
        surround.border_px,
        surround.margin_px,
        -float(offsets[0]) + beyond,
        float(offsets[-1]) + beyond,
    )


@compiled
def _surround_within(
    white: Array, border_px: Array, margin_px: Array, inner_reach: float, outer_reach: float
) -> tuple[Array, bool]:
    """``_surround_rows`` from the profiles' reach inwards and outwards (px)."""
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


def _level_design(
    n_profiles: int, groups: NDArray[np.intp] | None, along: Array | None
) -> tuple[Array, int]:
    """The levels' design W (R, K): a profile's dark level is W[:, k] . a_q, its contrast
    W[:, k] . b_q (one pair per group, and with ``along`` a slope along the side each); and
    the number of groups."""
    if groups is None and along is None:
        return np.ones((1, n_profiles)), 1
    g_of = np.zeros(n_profiles, np.intp) if groups is None else groups
    n_groups = int(g_of.max()) + 1
    member = (g_of[None, :] == np.arange(n_groups)[:, None]).astype(np.float64)  # (Q, K)
    W = member if along is None else np.vstack([member, member * along[None, :]])
    return W, n_groups


def _fit_side(
    values: Array,
    offsets: Array,
    iterations: int,
    pixels: Array,
    surround: _Surround | None = None,
    groups: NDArray[np.intp] | None = None,
    along: Array | None = None,
) -> tuple[Array, float] | None:
    """Edge offsets (K,) of K profiles (K, M) sampled at ``offsets`` (M,), dark to light, and
    the optical blur sigma (px, without the pixel's own square), or None without an edge.
    ``groups`` (K,): which dark and light levels each profile shares (default: one pair for
    all). ``along`` (K,): each profile's place along its side, -1 to 1; given, each group's
    levels also change linearly along it (vignetting and uneven light across a large marker).
    ``pixels``: the data to fit, (3, K, M): the offsets across the edge of the pixels nearest
    the samples, their values and how many samples each stands for (0 for a repeat;
    ``sample_profiles``). The samples themselves give the starting values only.

    Model: ``a + b * F(s - d_k)``, F a step blurred by ``sigma`` and integrated over the pixel
    (``step_model.pixel_step``), fitted to the pixels themselves at their exact offsets. A
    Gaussian step fitted to bilinearly interpolated samples instead locks the edge to the pixel
    grid by an amount that depends on where the edge falls in a pixel: on a 25 px marker turned
    0.5-2 deg from the pixel rows (noise-free), up to 0.19 deg of yaw at an optical blur of
    0.3 px and 0.016 deg at 0.6 px. With ``surround``, the model also holds the border's inner edge
    where the cell inside is white and the end of the white margin outside: blur mixes both
    into the profiles once they are within a few sigma, and left out they pull the edge (by
    0.1 px for a 30 px marker whose margin is under a cell, at a blur of 1.1 px). Gauss-Newton
    from the midpoint crossings on all parameters at once: each ``d_k`` touches only its own
    profile, so the normal equations are solved through the Schur complement of the shared
    parameters (dark level, contrast, margin drop and log sigma)."""
    lo, hi, d, rise = profile_start(values, offsets)
    if not hi - lo > MIN_CONTRAST:
        return None
    W, n_groups = _level_design(values.shape[0], groups, along)
    # each group's dark level and contrast to start from; their slopes along the side at 0
    levels = np.zeros((2, W.shape[0]))
    levels[:, :n_groups] = [[lo], [hi - lo]]
    log_sigma = math.log(_first_blur_px(rise, float(offsets[1] - offsets[0]), hi - lo))
    around, with_margin = _surround_rows(surround, offsets, math.exp(log_sigma), len(d))
    ok, log_sigma = fit_steps(pixels, d, W, levels, log_sigma, around, with_margin, iterations)
    if not ok:
        return None
    return d, math.exp(log_sigma)


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


def _inner_cells_white(cells: NDArray[np.uint8], t: Array) -> Array:
    """(4, K): whether the cell just inside the border is white at fractions ``t`` along each
    side, sides in ArUco corner order (top left to right, right downwards, bottom right to
    left, left upwards; ``cells`` row 0 is the top)."""
    n = cells.shape[0]
    j = np.clip(np.floor(t * n).astype(np.intp), 0, n - 1)
    back = n - 1 - j
    return np.stack([cells[1, j], cells[j, n - 2], cells[n - 2, back], cells[back, 1]]).astype(
        np.float64
    )


@functools.lru_cache(maxsize=256)
def _side_fractions(
    K: int, trim: float, n_cells: int, cells_bytes: bytes | None
) -> tuple[Array, Array]:
    """Where K profiles cross each side, as fractions of it (K,), and whether the cell just
    inside the border is white there (4K, sides one after the other; 0 everywhere without the
    cells: ``cells_bytes`` None, else the (n_cells, n_cells) uint8 cells' bytes). The same
    for every frame of a marker, so kept (read-only)."""
    t = np.linspace(trim, 1.0 - trim, K)
    if cells_bytes is None:
        white = np.zeros(4 * K)
    else:
        cells = np.frombuffer(cells_bytes, np.uint8).reshape(n_cells, n_cells)
        white = _inner_cells_white(cells, t).ravel()
    t.setflags(write=False)
    white.setflags(write=False)
    return t, white


@dataclass(frozen=True)
class EdgeFit:
    """A marker's corners (4, 2) from its fitted border edges, the blur sigma the fit found
    (pixels; with the pixels' own area in it), and the corners' covariance (8, 8; px^2,
    x0, y0, x1, ...) from the edge points' scatter about the fitted sides."""

    corners_px: Array
    blur_px: float
    covariance_px2: Array


_STEP_N = 1e-6  # normalised-plane step of the lens model's numerical Jacobian


def _corners_of_lines(
    camera: CameraModel,
    normals: Array,
    offsets: Array,
    centres: Array,
    angle_var: Array,
    shift_var: Array,
) -> tuple[Array, Array] | None:
    """The four corners where the side lines fitted by ``fit_lines`` meet, in pixels (4, 2),
    and their covariance (8, 8; px^2, x0, y0, x1, ...) from the lines' own; None where two
    lines are parallel or a corner does not project."""
    met, corners_n, A_inv = intersect_sides(normals, offsets)
    if not met:
        return None
    # the normalised plane to pixels, at each corner and a step along x and y
    projected, ok = camera.project(corner_probes(corners_n, _STEP_N))
    if not ok.all():
        return None
    corners_px, lens = lens_jacobians(np.ascontiguousarray(projected, np.float64), _STEP_N)
    covariance = corner_covariance(lens, A_inv, corners_n, normals, centres, angle_var, shift_var)
    return corners_px, covariance


def outside_reach_px(cell_px: float, settings: EdgeFitSettings | None = None) -> float:
    """How far (px) the profiles reach outwards from the start of a marker with cells of
    ``cell_px``."""
    cfg = settings or EdgeFitSettings()
    return min(cfg.max_window_px, max(cfg.min_window_px, cfg.outside_cells * cell_px))


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
    that is within reach of the profiles its end enters the model too."""
    cfg = settings or EdgeFitSettings()
    corners = np.ascontiguousarray(corners_px, np.float64).reshape(4, 2)
    sides_px = side_lengths(corners)
    n_cells = cells if isinstance(cells, int) else int(cells.shape[0])
    cell_px = 0.25 * float(sides_px.sum()) / n_cells
    reach_in = min(cfg.max_window_px, max(cfg.min_window_px, cfg.inside_cells * cell_px))
    reach_out = outside_reach_px(cell_px, cfg)
    step = max(cfg.step_px, (reach_in + reach_out) / (cfg.max_samples - 1))
    offsets = np.arange(-reach_in, reach_out + 1e-9, step)
    xy = camera.normalize(corners)
    if not np.isfinite(xy).all():
        return None
    # K points along each side, all four sides at once: (4, K) -> flattened (4K,)
    K = int(min(cfg.max_profiles, max(4.0, float(sides_px.min()) / 2.0)))
    printed = None if isinstance(cells, int) else np.ascontiguousarray(cells, np.uint8).tobytes()
    t, white = _side_fractions(K, cfg.trim, n_cells, printed)
    p_n, step_n, perp_n, probes = side_probes(xy, t)
    projected, ok = camera.project(probes)
    if not ok.all():
        return None
    projected = np.ascontiguousarray(projected, np.float64)
    centre_x, centre_y = 0.25 * corners.sum(axis=0)
    normal = outward_normals(projected, float(centre_x), float(centre_y))
    # bilinear samples to start from; the fit's data: the pixel nearest each sample, at its
    # own offset across the edge
    values, pixels, rows = sample_profiles(grey, projected[: 4 * K], normal, offsets)
    if np.count_nonzero(rows) < 12:
        return None
    # a cell's width across side i: the perpendicular sides' lengths over n
    across = np.repeat((sides_px[[3, 0, 1, 2]] + sides_px[[1, 2, 3, 0]]) / (2.0 * n_cells), K)
    margins = np.full(4, np.inf) if margin_cells is None else np.asarray(margin_cells, float)
    surround = _Surround(white[rows], across[rows], (np.repeat(margins, K) * across)[rows])
    sides = along = None
    if float(sides_px.min()) >= cfg.own_levels_from_px:
        sides = np.repeat(np.arange(4), K)[rows]
        along = np.tile(2.0 * t - 1.0, 4)[rows]
    # a fit that diverges on a poor profile overflows on its way; its result is checked
    # (finite edges, positive contrast) and refused, so numpy's warnings would only be noise
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        fit = _fit_side(
            values[rows],
            offsets,
            cfg.iterations,
            pixels[:, rows],
            surround,
            sides,
            along,
        )
    if fit is None:
        return None
    d = np.full(4 * K, np.nan)
    d[rows], optical_blur_px = fit
    blur_px = math.sqrt(optical_blur_px**2 + 1.0 / 12.0)
    good = np.isfinite(d) & (d > -reach_in) & (d < reach_out)
    edge_n = edge_points_n(p_n, step_n, perp_n, projected, normal, d)
    fitted, *lines = fit_lines(edge_n.reshape(4, K, 2), good.reshape(4, K))
    refined = _corners_of_lines(camera, *lines) if fitted else None
    if refined is None or largest_move(refined[0], corners) > cfg.max_shift_cells * cell_px:
        return None
    return EdgeFit(refined[0], blur_px, refined[1])
