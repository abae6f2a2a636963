"""Marker corners from the marker's four border edges, fitted through the lens model.

A corner found by gradient methods (OpenCV's SUBPIX, ``cornerSubPix``) sits a fraction of a
pixel inside the true corner of a blurred square: the blur rounds the corner and the gradient
structure there is no longer that of two straight edges. The edges themselves are not biased by
a symmetric blur: across an edge, the image is a step convolved with the blur, whose midpoint
is the edge. So each side of the marker's outer border is fitted, then the corners are the
intersections of neighbouring sides.

Per side, intensity profiles are sampled across the edge (bilinear) at points spaced along it,
and fitted together with ``a + b * Phi((s - d_k) / sigma)``: one edge offset ``d_k`` per profile,
and dark level ``a``, contrast ``b`` and blur ``sigma`` shared by the marker (Gauss-Newton).
The edge points are taken to the camera's normalised image plane, where a straight edge of the
printed square is a straight line for any lens model, and a line is fitted to them (total least
squares, outliers trimmed). Corners are intersected there and projected back to pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel

Array = NDArray[np.float64]
_SQRT2 = math.sqrt(2.0)
# Abramowitz and Stegun 7.1.26: erf to 1.5e-7
_ERF_P = 0.3275911
_ERF_A = (0.254829592, -0.284496736, 1.421413741, -1.453152027, 1.061405429)


@dataclass(frozen=True)
class EdgeFitSettings:
    """inside_cells, outside_cells : how far the profiles reach across the edge into the black
    border (one cell wide, so well under 1) and into the white margin, in marker cells.
    min/max_window_px : bounds of those reaches. step_px : sampling step along a profile,
    widened to keep at most max_samples per profile. max_profiles : profiles per side (one per
    2 px of side below that). trim : fraction of each side left out at both ends (the corners'
    neighbourhoods). max_shift_cells : a fitted corner further than this from its start is
    rejected (the start is kept). iterations : rounds of the step-model fit."""

    inside_cells: float = 0.45
    outside_cells: float = 0.7
    min_window_px: float = 1.0
    max_window_px: float = 8.0
    step_px: float = 0.35
    max_samples: int = 14
    max_profiles: int = 24
    trim: float = 0.1
    max_shift_cells: float = 0.4
    iterations: int = 4


def _phi_pdf(u: Array) -> tuple[Array, Array]:
    """Standard normal CDF and density of ``u`` (the CDF via Abramowitz and Stegun 7.1.26,
    which shares its exponential with the density)."""
    z = np.abs(u) * (1.0 / _SQRT2)
    t = 1.0 / (1.0 + _ERF_P * z)
    a1, a2, a3, a4, a5 = _ERF_A
    gauss = np.exp(-z * z)
    erf = 1.0 - t * (a1 + t * (a2 + t * (a3 + t * (a4 + t * a5)))) * gauss
    return 0.5 + 0.5 * np.copysign(erf, u), gauss * (1.0 / math.sqrt(2.0 * math.pi))


def _fit_side(
    values: Array, offsets: Array, iterations: int
) -> tuple[Array, float, float, float] | None:
    """Edge offsets (K,) of K profiles (K, M) sampled at ``offsets`` (M,), dark to light, and
    the shared dark level, contrast and blur: (d, a, b, sigma), or None without an edge.

    Block Gauss-Newton from the midpoint crossings: each round takes a Newton step for every
    ``d_k`` (independent given the shared parameters), solves ``a, b`` (linear), and takes a
    Newton step for ``log sigma``. (Modelling the border's inner edge one cell further in, which
    blur mixes into the profiles of small markers, was tried and did not lower the error.)"""
    K, M = values.shape
    lo = float(values[:, : max(1, M // 4)].mean())
    hi = float(values[:, -max(1, M // 4) :].mean())
    if not hi - lo > 4.0:
        return None
    a, b, sigma = lo, hi - lo, 0.8
    d = _midpoint_crossings(values, offsets, lo + 0.5 * b)
    n = float(K * M)
    for _ in range(iterations):
        u = (offsets[None, :] - d[:, None]) * (1.0 / sigma)
        Phi, pdf = _phi_pdf(u)
        r = a + b * Phi - values
        # every d_k: dr/dd_k = -b pdf / sigma
        J_d = pdf * (-b / sigma)
        step_d = (J_d * r).sum(axis=1) / ((J_d * J_d).sum(axis=1) + 1e-12)
        d = d - np.minimum(np.maximum(step_d, -1.0), 1.0)
        # a and b: linear least squares (with the model as it was before the d step)
        s1, s2 = float(Phi.sum()), float((Phi * Phi).sum())
        v1, v2 = float(values.sum()), float((Phi * values).sum())
        det = n * s2 - s1 * s1
        if abs(det) < 1e-9:
            return None
        a, b = (s2 * v1 - s1 * v2) / det, (n * v2 - s1 * v1) / det
        # log sigma: dr/dlog(sigma) = -b pdf u
        r = a + b * Phi - values
        J_s = pdf * u * (-b)
        step_s = float((J_s * r).sum()) / (float((J_s * J_s).sum()) + 1e-12)
        sigma = min(6.0, max(0.2, sigma * math.exp(-min(0.5, max(-0.5, step_s)))))
        if float(np.max(np.abs(step_d))) < 2e-3:
            break
    if not (b > 0 and np.all(np.isfinite(d))):
        return None
    return d, a, b, sigma


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


def _bilinear(grey: NDArray[np.uint8], points_px: Array) -> Array:
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


def _lines_tls(points: Array, usable: NDArray[np.bool_]) -> tuple[Array, Array] | None:
    """Lines n . x = c through each of S sets of 2-D points (S, K, 2) where ``usable`` (S, K):
    total least squares, then again without the points beyond 3 RMS. Returns normals (S, 2) and
    offsets (S,), or None when a set has under 3 points."""
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
    return normals, offsets


def refine_corners_edges(
    grey: NDArray[np.uint8],
    corners_px: Array,
    camera: CameraModel,
    cells: int,
    settings: EdgeFitSettings | None = None,
) -> Array | None:
    """Corners (4, 2) of a marker from its four fitted border edges, or None if a side cannot
    be fitted or a corner would move too far from ``corners_px`` (a good start, e.g. from
    ``cornerSubPix``). ``cells``: cells across the marker, border included."""
    cfg = settings or EdgeFitSettings()
    corners = np.asarray(corners_px, np.float64).reshape(4, 2)
    sides_px = np.linalg.norm(corners[[1, 2, 3, 0]] - corners, axis=1)
    cell_px = float(sides_px.mean()) / cells
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
    outward = np.sign((normal * (p_px - corners.mean(axis=0))).sum(axis=1))[:, None]
    normal = normal * np.where(outward == 0, 1.0, outward)
    samples = p_px[:, None, :] + offsets[None, :, None] * normal[:, None, :]
    values = _bilinear(grey, samples)
    rows = np.all(np.isfinite(values), axis=1)
    if np.count_nonzero(rows) < 12:
        return None
    fit = _fit_side(values[rows], offsets, cfg.iterations)
    if fit is None:
        return None
    d = np.full(4 * K, np.nan)
    d[rows] = fit[0]
    good = np.isfinite(d) & (d > -reach_in) & (d < reach_out)
    # the edge points in the normalised plane, through the lens model's local Jacobian at each
    # sample (the offsets are a pixel or two: the linearisation error is far below 1e-3 px)
    shift_px = np.nan_to_num(d)[:, None] * normal
    b1, b2 = q_px - p_px, r_px - p_px  # images of step_n and perp_n
    det = b1[:, 0] * b2[:, 1] - b1[:, 1] * b2[:, 0]
    c1 = (shift_px[:, 0] * b2[:, 1] - shift_px[:, 1] * b2[:, 0]) / det
    c2 = (b1[:, 0] * shift_px[:, 1] - b1[:, 1] * shift_px[:, 0]) / det
    edge_n = p_n + c1[:, None] * step_n + c2[:, None] * perp_n
    fitted = _lines_tls(edge_n.reshape(4, K, 2), good.reshape(4, K))
    if fitted is None:
        return None
    normals, line_offsets = fitted
    # corner i joins side i - 1 (from corner i - 1) and side i (to corner i + 1)
    previous = [3, 0, 1, 2]
    A = np.stack([normals[previous], normals], axis=1)  # (4, 2, 2)
    if np.any(np.abs(np.linalg.det(A)) < 1e-12):
        return None
    refined_n = np.linalg.solve(A, np.stack([line_offsets[previous], line_offsets], 1)[..., None])
    refined_n = refined_n[..., 0]
    refined_px, ok = camera.project(np.hstack([refined_n, np.ones((4, 1))]))
    if not np.all(ok):
        return None
    if np.max(np.linalg.norm(refined_px - corners, axis=1)) > cfg.max_shift_cells * cell_px:
        return None
    return np.asarray(refined_px, np.float64)
