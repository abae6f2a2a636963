"""Marker corners from the marker's four border edges, fitted through the lens model.

A corner found by gradient methods (OpenCV's SUBPIX, ``cornerSubPix``) sits a fraction of a
pixel inside the true corner of a blurred square: the blur rounds the corner and the gradient
structure there is no longer that of two straight edges. The edges themselves are not biased by
a symmetric blur: across an edge, the image is a step convolved with the blur, whose midpoint
is the edge. So each side of the marker's outer border is fitted, then the corners are the
intersections of neighbouring sides.

Per side, profiles run across the edge at points spaced along it. Each takes the pixels nearest
points spaced along the profile, at their centres' own offsets from the edge, and they are fitted
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

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.step_model import MAX_BLUR_PX, MIN_BLUR_PX, MIN_CONTRAST, fit_steps

Array = NDArray[np.float64]
_SQRT2 = math.sqrt(2.0)


@dataclass(frozen=True)
class EdgeFitSettings:
    """inside_cells, outside_cells : how far the profiles reach across the edge into the black
    border (one cell wide, so well under 1) and into the white margin, in marker cells.
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


def _first_blur_px(values: Array, offsets: Array, contrast: float) -> float:
    """A first guess of the optical blur sigma (px) from the profiles' steepest rise."""
    # the blur from the steepest rise between samples h apart, which for an edge midway
    # between them is b * erf(h / (2 sqrt(2) sigma))
    h = float(offsets[1] - offsets[0])
    rise = float(np.mean(np.max(np.diff(values, axis=1), axis=1))) / contrast
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
    rows = np.zeros((3, n_profiles))
    rows[2] = 1e6
    if surround is None:
        return rows, False
    beyond = _BEYOND_REACH_SIGMAS * sigma_px + 0.5
    reach_in = surround.border_px < -float(offsets[0]) + beyond
    rows[0] = np.where(reach_in, surround.white_inside, 0.0)
    rows[1] = surround.border_px
    near = surround.margin_px < float(offsets[-1]) + beyond
    rows[2] = np.where(near, surround.margin_px, 1e6)
    return rows, bool(np.any(near))


def _level_design(
    n_profiles: int, groups: NDArray[np.intp] | None, along: Array | None
) -> tuple[Array, int]:
    """The levels' design W (R, K): a profile's dark level is W[:, k] . a_q, its contrast
    W[:, k] . b_q (one pair per group, and with ``along`` a slope along the side each); and
    the number of groups."""
    g_of = np.zeros(n_profiles, np.intp) if groups is None else groups
    n_groups = int(g_of.max()) + 1
    member = (g_of[None, :] == np.arange(n_groups)[:, None]).astype(np.float64)  # (Q, K)
    W = member if along is None else np.vstack([member, member * along[None, :]])
    return W, n_groups


def _fit_side(
    values: Array,
    offsets: Array,
    iterations: int,
    pixels: tuple[Array, Array],
    surround: _Surround | None = None,
    groups: NDArray[np.intp] | None = None,
    along: Array | None = None,
) -> tuple[Array, float] | None:
    """Edge offsets (K,) of K profiles (K, M) sampled at ``offsets`` (M,), dark to light, and
    the optical blur sigma (px, without the pixel's own square), or None without an edge.
    ``groups`` (K,): which dark and light levels each profile shares (default: one pair for
    all). ``along`` (K,): each profile's place along its side, -1 to 1; given, each group's
    levels also change linearly along it (vignetting and uneven light across a large marker).
    ``pixels``: the data to fit, (K, M) offsets across the edge of whole pixels' centres
    and (K, M) their values (the samples give the starting values only).

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
    M = values.shape[1]
    lo = float(values[:, : max(1, M // 4)].mean())
    hi = float(values[:, -max(1, M // 4) :].mean())
    if not hi - lo > MIN_CONTRAST:
        return None
    W, n_groups = _level_design(values.shape[0], groups, along)
    # each group's dark level and contrast to start from; their slopes along the side at 0
    levels = np.zeros((2, W.shape[0]))
    levels[:, :n_groups] = [[lo], [hi - lo]]
    d = _midpoint_crossings(values, offsets, lo + 0.5 * (hi - lo))
    log_sigma = math.log(_first_blur_px(values, offsets, hi - lo))
    around, with_margin = _surround_rows(surround, offsets, math.exp(log_sigma), len(d))
    ok, log_sigma = fit_steps(
        np.stack(pixels), d, W, levels, log_sigma, around, with_margin, iterations
    )
    if not ok:
        return None
    return d, math.exp(log_sigma)


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


def _midpoint_crossings(values: Array, offsets: Array, level: float) -> Array:
    """Per profile, where it crosses ``level`` (linear interpolation; the crossing nearest the
    profile's middle when noise makes several)."""
    above = values >= level
    change = above[:, 1:] != above[:, :-1]  # (K, M-1): a crossing between j and j+1
    v0, v1 = values[:, :-1], values[:, 1:]
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.minimum(np.maximum((level - v0) / (v1 - v0), 0.0), 1.0)
    position = offsets[:-1] + frac * (offsets[1:] - offsets[:-1])
    distance = np.where(change, np.abs(position), np.inf)
    j = np.argmin(distance, axis=1)
    rows = np.arange(values.shape[0])
    return np.where(np.isfinite(distance[rows, j]), position[rows, j], 0.0)


def bilinear(grey: NDArray[np.uint8], points_px: Array) -> Array:
    """Bilinear interpolation of ``grey`` at ``points_px`` (..., 2), NaN where a point's four
    neighbours are not all in the image. (Exact positions: ``cv2.remap`` rounds them to 1/32
    of a pixel.)"""
    h, w = grey.shape[:2]
    x, y = points_px[..., 0], points_px[..., 1]
    ix, iy = np.floor(x), np.floor(y)
    inside = (ix >= 0) & (iy >= 0) & (ix < w - 1) & (iy < h - 1)
    i = np.where(inside, iy, 0).astype(np.intp) * w + np.where(inside, ix, 0).astype(np.intp)
    flat = grey.reshape(-1)
    fx, fy = x - ix, y - iy
    top = flat[i] + fx * (flat[i + 1] - flat[i].astype(np.float64))
    bottom = flat[i + w] + fx * (flat[i + w + 1] - flat[i + w].astype(np.float64))
    return np.where(inside, top + fy * (bottom - top), np.nan)


@dataclass(frozen=True)
class _Lines:
    """S lines n . x = c (``normals`` (S, 2), ``offsets`` (S,)) fitted to points, with what
    the points' scatter about them says of their uncertainty: each line's centre (S, 2), the
    variance of its angle (rad^2) and of its shift along the normal at the centre (S,)."""

    normals: Array
    offsets: Array
    centres: Array
    angle_var: Array
    shift_var: Array


def _lines_tls(points: Array, usable: NDArray[np.bool_]) -> _Lines | None:
    """Lines n . x = c through each of S sets of 2-D points (S, K, 2) where ``usable`` (S, K):
    total least squares, then again without the points beyond 3 RMS; or None when a set has
    under 3 points. The points' scatter normal to their line (with 2 degrees of freedom
    taken by the line) gives the line's uncertainty, as for independent points: its shift at
    the centre has variance s^2 / n, its angle s^2 / sum(along^2)."""
    keep = usable.copy()
    normals = np.zeros((points.shape[0], 2))
    offsets = np.zeros(points.shape[0])
    for _ in range(2):
        weight = keep.astype(np.float64)
        count = weight.sum(axis=1)
        if np.any(count < 3):
            return None
        centre = np.einsum("sk,skj->sj", weight, points) / count[:, None]
        q = (points - centre[:, None, :]) * weight[..., None]
        sxx = np.einsum("sk,sk->s", q[..., 0], q[..., 0])
        syy = np.einsum("sk,sk->s", q[..., 1], q[..., 1])
        sxy = np.einsum("sk,sk->s", q[..., 0], q[..., 1])
        # the line runs along the scatter's major axis; its normal is perpendicular
        angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
        normals = np.stack([-np.sin(angle), np.cos(angle)], axis=1)
        offsets = np.einsum("sj,sj->s", normals, centre)
        residual = np.einsum("skj,sj->sk", points, normals) - offsets[:, None]
        rms = np.sqrt((residual * residual * weight).sum(axis=1) / count) + 1e-12
        keep = usable & (np.abs(residual) < 3.0 * rms[:, None])
    scatter = (residual * residual * weight).sum(axis=1) / np.maximum(count - 2.0, 1.0)
    direction = np.stack([normals[:, 1], -normals[:, 0]], axis=1)
    along = np.einsum("skj,sj->sk", points - centre[:, None, :], direction)
    spread = np.maximum((along * along * weight).sum(axis=1), 1e-30)
    return _Lines(normals, offsets, centre, scatter / spread, scatter / count)


@dataclass(frozen=True)
class EdgeFit:
    """A marker's corners (4, 2) from its fitted border edges, the blur sigma the fit found
    (pixels; with the pixels' own area in it), and the corners' covariance (8, 8; px^2,
    x0, y0, x1, ...) from the edge points' scatter about the fitted sides."""

    corners_px: Array
    blur_px: float
    covariance_px2: Array


@dataclass(frozen=True)
class _Profiles:
    """Points along a marker's four sides (4K, flattened side by side) in the normalised plane
    (``p_n``) and in pixels (``p_px``), the normalised steps along and across each side
    (``step_n``, ``perp_n``) and their images (``q_px``, ``r_px``: ``p_n`` plus each step), and
    each point's outward unit normal in the image (``normal``)."""

    p_n: Array
    step_n: Array
    perp_n: Array
    p_px: Array
    q_px: Array
    r_px: Array
    normal: Array

    @staticmethod
    def along_sides(
        camera: CameraModel, corners_px: Array, xy: Array, t: Array
    ) -> _Profiles | None:
        """Points at fractions ``t`` (K,) of each side from normalised corners ``xy``; None
        where one does not project."""
        K = len(t)
        a_n = xy[:, None, :]
        b_n = xy[[1, 2, 3, 0]][:, None, :]
        p_n = (a_n + t[None, :, None] * (b_n - a_n)).reshape(-1, 2)
        step_n = np.repeat((xy[[1, 2, 3, 0]] - xy) * 1e-3, K, axis=0)
        perp_n = np.stack([-step_n[:, 1], step_n[:, 0]], 1)
        ones = np.ones((4 * K, 1))
        all_px, ok = camera.project(
            np.vstack([np.hstack([p, ones]) for p in (p_n, p_n + step_n, p_n + perp_n)])
        )
        if not np.all(ok):
            return None
        p_px, q_px, r_px = all_px[: 4 * K], all_px[4 * K : 8 * K], all_px[8 * K :]
        tangent = q_px - p_px
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        normal = np.stack([tangent[:, 1], -tangent[:, 0]], 1)
        outward = np.sign((normal * (p_px - corners_px.mean(axis=0))).sum(axis=1))[:, None]
        normal = normal * np.where(outward == 0, 1.0, outward)
        return _Profiles(p_n, step_n, perp_n, p_px, q_px, r_px, normal)

    def edge_points_n(self, d_px: Array) -> Array:
        """The edge points (4K, 2) in the normalised plane, ``d_px`` along each normal (NaN:
        none), through the lens model's local Jacobian at each point (the offsets are a pixel
        or two: the linearisation error is far below 1e-3 px)."""
        shift_px = np.nan_to_num(d_px)[:, None] * self.normal
        b1, b2 = self.q_px - self.p_px, self.r_px - self.p_px  # images of step_n and perp_n
        det = b1[:, 0] * b2[:, 1] - b1[:, 1] * b2[:, 0]
        c1 = (shift_px[:, 0] * b2[:, 1] - shift_px[:, 1] * b2[:, 0]) / det
        c2 = (b1[:, 0] * shift_px[:, 1] - b1[:, 1] * shift_px[:, 0]) / det
        edge_n: Array = self.p_n + c1[:, None] * self.step_n + c2[:, None] * self.perp_n
        return edge_n


_PREVIOUS = [3, 0, 1, 2]  # corner i joins side i - 1 (from corner i - 1) and side i
_STEP_N = 1e-6  # normalised-plane step of the lens model's numerical Jacobian


def _corners_of_lines(camera: CameraModel, lines: _Lines) -> tuple[Array, Array] | None:
    """The four corners where the fitted side lines meet, in pixels (4, 2), and their
    covariance (8, 8; px^2, x0, y0, x1, ...) from the lines' own; None where two lines are
    parallel or a corner does not project.

    A corner moves with the two lines through it: a line's shift moves both its corners
    alike, its turn moves them apart, so neighbouring corners' errors are correlated (on
    rendered markers the two corners of a side err against each other along its normal)."""
    normals, offsets = lines.normals, lines.offsets
    A = np.stack([normals[_PREVIOUS], normals], axis=1)  # (4, 2, 2)
    if np.any(np.abs(np.linalg.det(A)) < 1e-12):
        return None
    A_inv = np.linalg.inv(A)
    corners_n = np.einsum("iab,ib->ia", A_inv, np.stack([offsets[_PREVIOUS], offsets], 1))
    # the normalised plane to pixels, at each corner and a step along x and y
    probes = np.concatenate([corners_n, corners_n + [_STEP_N, 0.0], corners_n + [0.0, _STEP_N]])
    projected, ok = camera.project(np.hstack([probes, np.ones((12, 1))]))
    if not np.all(ok):
        return None
    corners_px = np.asarray(projected[:4], np.float64)
    lens = np.stack([projected[4:8] - corners_px, projected[8:] - corners_px], axis=2) / _STEP_N
    # d(corner) / d(angle, shift) of each side: the line n . x = c turns by a about its
    # centre m (dn = a * (-n_y, n_x)... = -a * u, u its direction) and shifts by e there
    # (dc = e - a * u . m); then A dx = dc - dn . x for the two lines through the corner
    direction = np.stack([normals[:, 1], -normals[:, 0]], axis=1)
    sides = np.stack([_PREVIOUS, np.arange(4)], axis=1)  # (4, 2): the sides through corner i
    # pixels per unit of each of the two lines' offsets, (4, 2 px, 2 lines)
    per_offset = lens @ A_inv
    lever = np.einsum("isj,isj->is", direction[sides], corners_n[:, None, :] - lines.centres[sides])
    G = np.zeros((4, 2, 4, 2))  # corner, px axis, side, (angle, shift)
    for row in range(2):
        G[np.arange(4), :, sides[:, row], 0] = per_offset[:, :, row] * lever[:, row, None]
        G[np.arange(4), :, sides[:, row], 1] = per_offset[:, :, row]
    G8 = G.reshape(8, 8)
    variances = np.stack([lines.angle_var, lines.shift_var], axis=1).reshape(8)
    return corners_px, (G8 * variances) @ G8.T


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
    corners = np.asarray(corners_px, np.float64).reshape(4, 2)
    sides_px = np.linalg.norm(corners[[1, 2, 3, 0]] - corners, axis=1)
    n_cells = cells if isinstance(cells, int) else int(cells.shape[0])
    cell_px = float(sides_px.mean()) / n_cells
    reach_in = min(cfg.max_window_px, max(cfg.min_window_px, cfg.inside_cells * cell_px))
    reach_out = min(cfg.max_window_px, max(cfg.min_window_px, cfg.outside_cells * cell_px))
    step = max(cfg.step_px, (reach_in + reach_out) / (cfg.max_samples - 1))
    offsets = np.arange(-reach_in, reach_out + 1e-9, step)
    xy = camera.normalize(corners)
    if not np.all(np.isfinite(xy)):
        return None
    # K points along each side, all four sides at once: (4, K) -> flattened (4K,)
    K = int(min(cfg.max_profiles, max(4.0, float(sides_px.min()) / 2.0)))
    t = np.linspace(cfg.trim, 1.0 - cfg.trim, K)
    profiles = _Profiles.along_sides(camera, corners, xy, t)
    if profiles is None:
        return None
    p_px, normal = profiles.p_px, profiles.normal
    samples = p_px[:, None, :] + offsets[None, :, None] * normal[:, None, :]
    values = bilinear(grey, samples)
    # the fit's data: the pixel nearest each sample, at its own offset across the edge
    nearest = np.round(samples)
    pixel_offsets = np.einsum("kmj,kj->km", nearest - p_px[:, None, :], normal)
    pixel_values = grey[
        np.clip(nearest[..., 1], 0, grey.shape[0] - 1).astype(np.intp),
        np.clip(nearest[..., 0], 0, grey.shape[1] - 1).astype(np.intp),
    ].astype(np.float64)
    rows = np.all(np.isfinite(values), axis=1)
    if np.count_nonzero(rows) < 12:
        return None
    # a cell's width across side i: the perpendicular sides' lengths over n
    across = np.repeat((sides_px[[3, 0, 1, 2]] + sides_px[[1, 2, 3, 0]]) / (2.0 * n_cells), K)
    white = np.zeros(4 * K) if isinstance(cells, int) else _inner_cells_white(cells, t).ravel()
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
            (pixel_offsets[rows], pixel_values[rows]),
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
    edge_n = profiles.edge_points_n(d)
    fitted = _lines_tls(edge_n.reshape(4, K, 2), good.reshape(4, K))
    refined = None if fitted is None else _corners_of_lines(camera, fitted)
    if refined is None or (
        np.max(np.linalg.norm(refined[0] - corners, axis=1)) > cfg.max_shift_cells * cell_px
    ):
        return None
    return EdgeFit(refined[0], blur_px, refined[1])
