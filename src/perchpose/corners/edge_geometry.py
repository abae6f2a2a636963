"""The edge fit's geometry, compiled: points along a marker's sides, the pixels that profiles
across them sample, the edge points in the normalised plane, and the lines and corners fitted
through those points with their uncertainty.

``corners.edge_fit`` calls these around its lens model (``CameraModel.project``, which may be
OpenCV's) and the blurred-step fit (``corners.step_model``). Each is a loop over a few hundred
points; written as numpy expressions they made dozens of small temporary arrays a marker, which
cost several times the arithmetic (``perchpose.numeric.jit``).

Sides run in ArUco corner order: side i from corner i to corner i + 1; corner i joins side
i - 1 and side i.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from perchpose.numeric.jit import compiled

Array = NDArray[np.float64]

# the normalised-plane steps along and across a side whose images give its local direction
# in pixels (a fraction of the side's own length)
SIDE_STEP = 1e-3


@compiled
def side_lengths(corners_px: Array) -> Array:
    """The lengths (4,) of a quad's sides, side i from corner i to corner i + 1."""
    out = np.empty(4)
    for i in range(4):
        j = (i + 1) % 4
        dx, dy = corners_px[j, 0] - corners_px[i, 0], corners_px[j, 1] - corners_px[i, 1]
        out[i] = math.hypot(dx, dy)
    return out


@compiled
def largest_move(a_px: Array, b_px: Array) -> float:
    """The largest distance between corresponding points of ``a_px`` and ``b_px`` (N, 2)."""
    out = 0.0
    for i in range(a_px.shape[0]):
        out = max(out, math.hypot(a_px[i, 0] - b_px[i, 0], a_px[i, 1] - b_px[i, 1]))
    return out


@compiled
def side_probes(xy: Array, t: Array) -> tuple[Array, Array, Array, Array]:
    """Points at fractions ``t`` (K,) of each side of the quad with normalised corners ``xy``
    (4, 2), sides one after the other (4K, 2); a step along each side and one across it
    (``SIDE_STEP`` of the side), each (4K, 2); and the points to project (12K, 3; z = 1): the
    points, then each plus its step along, then each plus its step across."""
    K = t.shape[0]
    n = 4 * K
    p_n = np.empty((n, 2))
    step_n = np.empty((n, 2))
    perp_n = np.empty((n, 2))
    probes = np.ones((3 * n, 3))
    for s in range(4):
        e = (s + 1) % 4
        sx = (xy[e, 0] - xy[s, 0]) * SIDE_STEP
        sy = (xy[e, 1] - xy[s, 1]) * SIDE_STEP
        for k in range(K):
            i = s * K + k
            x = xy[s, 0] + t[k] * (xy[e, 0] - xy[s, 0])
            y = xy[s, 1] + t[k] * (xy[e, 1] - xy[s, 1])
            p_n[i, 0], p_n[i, 1] = x, y
            step_n[i, 0], step_n[i, 1] = sx, sy
            perp_n[i, 0], perp_n[i, 1] = -sy, sx
            probes[i, 0], probes[i, 1] = x, y
            probes[n + i, 0], probes[n + i, 1] = x + sx, y + sy
            probes[2 * n + i, 0], probes[2 * n + i, 1] = x - sy, y + sx
    return p_n, step_n, perp_n, probes


@compiled
def outward_normals(projected: Array, centre_x: float, centre_y: float) -> Array:
    """Each side point's unit normal in the image (4K, 2), pointing away from the marker's
    centre (``centre_x``, ``centre_y``, px), from ``projected`` (12K, 2): the pixels of
    ``side_probes``'s points (the first 4K rows) and of their steps along (the next 4K)."""
    n = projected.shape[0] // 3
    normal = np.empty((n, 2))
    for i in range(n):
        tx = projected[n + i, 0] - projected[i, 0]
        ty = projected[n + i, 1] - projected[i, 1]
        length = math.hypot(tx, ty)
        if length > 0.0:
            tx, ty = tx / length, ty / length
        nx, ny = ty, -tx
        side = nx * (projected[i, 0] - centre_x) + ny * (projected[i, 1] - centre_y)
        if side < 0.0:
            nx, ny = -nx, -ny
        normal[i, 0], normal[i, 1] = nx, ny
    return normal


@compiled
def _round_half_even(x: float) -> float:
    """``x`` rounded to the nearest integer, halves to the even one (as ``numpy.round``)."""
    r = float(math.floor(x + 0.5))
    if r - x == 0.5 and r % 2.0 != 0.0:
        r -= 1.0
    return r


@compiled
def _bilinear_at(grey: NDArray[np.uint8], x: float, y: float) -> float:
    """Bilinear interpolation of ``grey`` at (``x``, ``y``) px, NaN where the four pixels
    around it are not all in the image."""
    h, w = grey.shape
    fx0, fy0 = math.floor(x), math.floor(y)
    if not (fx0 >= 0 and fy0 >= 0 and fx0 < w - 1 and fy0 < h - 1):
        return np.nan
    ix, iy = int(fx0), int(fy0)
    fx, fy = x - fx0, y - fy0
    g00, g01 = float(grey[iy, ix]), float(grey[iy, ix + 1])
    g10, g11 = float(grey[iy + 1, ix]), float(grey[iy + 1, ix + 1])
    top = g00 + fx * (g01 - g00)
    bottom = g10 + fx * (g11 - g10)
    return top + fy * (bottom - top)


@compiled
def sample_profiles(
    grey: NDArray[np.uint8], p_px: Array, normal: Array, offsets: Array
) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Profiles across the edge at ``p_px`` (N, 2) along ``normal`` (N, 2), sampled at
    ``offsets`` (M,) px: bilinear values (N, M; NaN where a sample's four neighbours are not
    all in the image); the pixels nearest the samples (3, N, M: each one's offset across the
    edge, its value, and how many of the profile's samples it is nearest, given at the first
    of them and 0 at the others, whose offset and value repeat it); and whether every sample
    of a profile is in the image (N,). Samples closer than a pixel share pixels, always
    consecutive ones (a pixel's nearest points are its square, which a straight profile
    crosses once): a fit weighting each pixel by its count is the fit to every sample, with
    fewer terms."""
    h, w = grey.shape
    N, M = p_px.shape[0], offsets.shape[0]
    values = np.empty((N, M))
    pixels = np.zeros((3, N, M))
    whole = np.ones(N, np.bool_)
    for k in range(N):
        px, py, nx, ny = p_px[k, 0], p_px[k, 1], normal[k, 0], normal[k, 1]
        first = 0
        last_x = last_y = -1.0
        for m in range(M):
            x = px + offsets[m] * nx
            y = py + offsets[m] * ny
            values[k, m] = _bilinear_at(grey, x, y)
            if not math.isfinite(values[k, m]):
                whole[k] = False
            rx, ry = _round_half_even(x), _round_half_even(y)
            pixels[0, k, m] = (rx - px) * nx + (ry - py) * ny
            cx = int(min(max(rx, 0.0), w - 1.0))
            cy = int(min(max(ry, 0.0), h - 1.0))
            pixels[1, k, m] = float(grey[cy, cx])
            if m > 0 and rx == last_x and ry == last_y:
                pixels[2, k, first] += 1.0
            else:
                first = m
                pixels[2, k, m] = 1.0
            last_x, last_y = rx, ry
    return values, pixels, whole


@compiled
def bilinear_points(grey: NDArray[np.uint8], points_px: Array) -> Array:
    """Bilinear interpolation of ``grey`` at ``points_px`` (N, 2), NaN where a point's four
    neighbours are not all in the image. (Exact positions: ``cv2.remap`` rounds them to 1/32
    of a pixel.)"""
    out = np.empty(points_px.shape[0])
    for i in range(points_px.shape[0]):
        out[i] = _bilinear_at(grey, points_px[i, 0], points_px[i, 1])
    return out


@compiled
def edge_points_n(
    p_n: Array, step_n: Array, perp_n: Array, projected: Array, normal: Array, d_px: Array
) -> Array:
    """The edge points (N, 2) in the normalised plane, ``d_px`` (N,) along each side point's
    ``normal`` (NaN: none, taken as 0), through the lens model's local Jacobian there: the
    images of ``step_n`` and ``perp_n`` (``projected``, as for ``outward_normals``) span it.
    The offsets are a pixel or two, so the linearisation errs far below 1e-3 px."""
    n = p_n.shape[0]
    out = np.empty((n, 2))
    for i in range(n):
        d = d_px[i] if math.isfinite(d_px[i]) else 0.0
        sx, sy = d * normal[i, 0], d * normal[i, 1]
        b1x = projected[n + i, 0] - projected[i, 0]
        b1y = projected[n + i, 1] - projected[i, 1]
        b2x = projected[2 * n + i, 0] - projected[i, 0]
        b2y = projected[2 * n + i, 1] - projected[i, 1]
        det = b1x * b2y - b1y * b2x
        if det == 0.0:
            out[i, 0] = out[i, 1] = np.nan
            continue
        c1 = (sx * b2y - sy * b2x) / det
        c2 = (b1x * sy - b1y * sx) / det
        out[i, 0] = p_n[i, 0] + c1 * step_n[i, 0] + c2 * perp_n[i, 0]
        out[i, 1] = p_n[i, 1] + c1 * step_n[i, 1] + c2 * perp_n[i, 1]
    return out


@compiled
def fit_lines(
    points: Array, usable: NDArray[np.bool_]
) -> tuple[bool, Array, Array, Array, Array, Array]:
    """Lines n . x = c through each of S sets of 2-D points (S, K, 2) where ``usable`` (S, K):
    total least squares, then again without the points beyond 3 RMS. Returns (whether every
    set had 3 points or more each time, normals (S, 2), offsets c (S,), centres (S, 2), the
    variance of each line's angle (rad^2) and of its shift along the normal at the centre
    (S,)).

    The points' scatter normal to their line (2 degrees of freedom taken by the line) gives
    the line's uncertainty, as for independent points: the shift at the centre has variance
    s^2 / n, the angle s^2 / sum(along^2)."""
    S, K = usable.shape
    normals = np.zeros((S, 2))
    offsets = np.zeros(S)
    centres = np.zeros((S, 2))
    angle_var = np.zeros(S)
    shift_var = np.zeros(S)
    residual = np.zeros(K)
    weight = np.zeros(K, np.bool_)
    for s in range(S):
        keep = usable[s].copy()
        count = mx = my = nx = ny = 0.0
        for _ in range(2):
            weight[:] = keep
            count = mx = my = 0.0
            for k in range(K):
                if weight[k]:
                    count += 1.0
                    mx += points[s, k, 0]
                    my += points[s, k, 1]
            if count < 3.0:
                return False, normals, offsets, centres, angle_var, shift_var
            mx /= count
            my /= count
            sxx = syy = sxy = 0.0
            for k in range(K):
                if weight[k]:
                    qx, qy = points[s, k, 0] - mx, points[s, k, 1] - my
                    sxx += qx * qx
                    syy += qy * qy
                    sxy += qx * qy
            # the line runs along the scatter's major axis; its normal is perpendicular
            angle = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
            nx, ny = -math.sin(angle), math.cos(angle)
            c = nx * mx + ny * my
            sum_r2 = 0.0
            for k in range(K):
                residual[k] = points[s, k, 0] * nx + points[s, k, 1] * ny - c
                if weight[k]:
                    sum_r2 += residual[k] * residual[k]
            rms = math.sqrt(sum_r2 / count) + 1e-12
            for k in range(K):
                keep[k] = usable[s, k] and abs(residual[k]) < 3.0 * rms
            normals[s, 0], normals[s, 1], offsets[s] = nx, ny, c
            centres[s, 0], centres[s, 1] = mx, my
        # the scatter about the line and the spread along it of the last round's points
        sum_r2 = spread = 0.0
        for k in range(K):
            if weight[k]:
                along = (points[s, k, 0] - mx) * ny - (points[s, k, 1] - my) * nx
                sum_r2 += residual[k] * residual[k]
                spread += along * along
        scatter = sum_r2 / max(count - 2.0, 1.0)
        angle_var[s] = scatter / max(spread, 1e-30)
        shift_var[s] = scatter / count
    return True, normals, offsets, centres, angle_var, shift_var


@compiled
def intersect_sides(normals: Array, offsets: Array) -> tuple[bool, Array, Array]:
    """Where the side lines n . x = c (``normals`` (4, 2), ``offsets`` (4,)) meet: corner i
    (4, 2) joins side i - 1 and side i; and each corner's inverse of the matrix of those two
    normals (4, 2, 2). False where two neighbouring sides are parallel."""
    corners = np.zeros((4, 2))
    A_inv = np.zeros((4, 2, 2))
    for i in range(4):
        j = (i + 3) % 4
        a, b = normals[j, 0], normals[j, 1]
        c, d = normals[i, 0], normals[i, 1]
        det = a * d - b * c
        if abs(det) < 1e-12:
            return False, corners, A_inv
        A_inv[i, 0, 0], A_inv[i, 0, 1] = d / det, -b / det
        A_inv[i, 1, 0], A_inv[i, 1, 1] = -c / det, a / det
        corners[i, 0] = A_inv[i, 0, 0] * offsets[j] + A_inv[i, 0, 1] * offsets[i]
        corners[i, 1] = A_inv[i, 1, 0] * offsets[j] + A_inv[i, 1, 1] * offsets[i]
    return True, corners, A_inv


@compiled
def corner_probes(corners_n: Array, step_n: float) -> Array:
    """Points (12, 3) on the plane z = 1 whose images give the lens's Jacobian at four
    corners (4, 2) of the normalised plane: the corners, then each a step ``step_n`` along x,
    then along y."""
    probes = np.ones((12, 3))
    for i in range(4):
        for k in range(3):
            probes[4 * k + i, 0] = corners_n[i, 0]
            probes[4 * k + i, 1] = corners_n[i, 1]
        probes[4 + i, 0] += step_n
        probes[8 + i, 1] += step_n
    return probes


@compiled
def lens_jacobians(projected: Array, step_n: float) -> tuple[Array, Array]:
    """From the images (12, 2) of ``corner_probes``: the corners in pixels (4, 2) and the
    lens's Jacobian at each (4, 2, 2; d pixel / d normalised x, y), by forward differences."""
    corners_px = projected[:4].copy()
    lens = np.empty((4, 2, 2))
    for i in range(4):
        for axis in range(2):
            lens[i, axis, 0] = (projected[4 + i, axis] - corners_px[i, axis]) / step_n
            lens[i, axis, 1] = (projected[8 + i, axis] - corners_px[i, axis]) / step_n
    return corners_px, lens


@compiled
def corner_covariance(
    lens: Array,
    A_inv: Array,
    corners_n: Array,
    normals: Array,
    centres: Array,
    angle_var: Array,
    shift_var: Array,
) -> Array:
    """The corners' covariance (8, 8; px^2, x0, y0, x1, ...) from their sides' angle and shift
    variances; ``lens`` (4, 2, 2): pixels per normalised unit at each corner, ``A_inv`` and
    ``corners_n`` from ``intersect_sides``.

    A side line n . x = c that turns by a about its centre m and shifts by e there moves n by
    -a u (u its direction) and c by e - a u . m, so each corner it passes through moves by
    A^-1 (dc - dn . x): a shift moves both its corners alike, a turn moves them apart, and
    neighbouring corners' errors are correlated through the side they share."""
    G = np.zeros((8, 8))  # corner px axes, then (angle, shift) of each side
    for i in range(4):
        for row in range(2):
            side = (i + 3) % 4 if row == 0 else i
            ux, uy = normals[side, 1], -normals[side, 0]
            lever = ux * (corners_n[i, 0] - centres[side, 0])
            lever += uy * (corners_n[i, 1] - centres[side, 1])
            for axis in range(2):
                per_offset = lens[i, axis, 0] * A_inv[i, 0, row]
                per_offset += lens[i, axis, 1] * A_inv[i, 1, row]
                G[2 * i + axis, 2 * side] = per_offset * lever
                G[2 * i + axis, 2 * side + 1] = per_offset
    out = np.zeros((8, 8))
    for a in range(8):
        for b in range(8):
            total = 0.0
            for p in range(4):
                total += G[a, 2 * p] * G[b, 2 * p] * angle_var[p]
                total += G[a, 2 * p + 1] * G[b, 2 * p + 1] * shift_var[p]
            out[a, b] = total
    return out
