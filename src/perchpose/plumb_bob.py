"""OpenCV's standard lens model (``plumb_bob``: radial k1-k6 as a ratio, tangential p1, p2,
thin prism s1-s4), compiled: the projection with its Jacobian, and its inverse.

``CameraModel`` used ``cv2.projectPoints`` and ``cv2.undistortPoints`` for it: a few corners at
a time, most of their cost was the call itself (tens of microseconds), several times a frame.
These give OpenCV's answers (projection to 1e-10 px, the inverse to the same convergence) for
4, 5, 8 and 12 coefficients; the tilted sensor's 14 stay with OpenCV. Like OpenCV, the
projection uses fx, fy, cx and cy of K and not its skew.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from perchpose.jit import compiled

Array = NDArray[np.float64]

# the coefficient counts these functions take (padded with zeros to 12); 14 has a tilt
COMPILED_LENGTHS = (4, 5, 8, 12)
# a point this close to the camera's plane (z, m) or behind it does not project
MIN_Z_M = 1e-9
# the inverse's Newton steps end below this (normalised units) or after this many
_STEP_DONE = 1e-15
_MAX_NEWTON = 50


def padded(dist: Array) -> Array:
    """``dist`` (4, 5, 8 or 12 coefficients, OpenCV's order) as 12: k1, k2, p1, p2, k3, k4,
    k5, k6, s1, s2, s3, s4."""
    out = np.zeros(12)
    out[: dist.size] = dist
    return out


@compiled
def _distorted(x: float, y: float, d: Array) -> tuple[float, float, float, float, float, float]:
    """The distorted normalised point of (x, y) and its Jacobian (d xd/dx, d xd/dy,
    d yd/dx, d yd/dy)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7]
    s1, s2, s3, s4 = d[8], d[9], d[10], d[11]
    r2 = x * x + y * y
    r4 = r2 * r2
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    # d radial / d r2
    slope = ((k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)) * den
             - num * (k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2))) / (den * den)  # fmt: skip
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + s3 * r2 + s4 * r4
    prism_x = s1 + 2.0 * s2 * r2
    prism_y = s3 + 2.0 * s4 * r2
    a = radial + 2.0 * x * x * slope + 2.0 * p1 * y + 6.0 * p2 * x + 2.0 * x * prism_x
    b = 2.0 * x * y * slope + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * y * prism_x
    c = 2.0 * x * y * slope + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * x * prism_y
    e = radial + 2.0 * y * y * slope + 6.0 * p1 * y + 2.0 * p2 * x + 2.0 * y * prism_y
    return xd, yd, a, b, c, e


@compiled
def project_with_jacobian(p: Array, K: Array, d: Array) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Pixels (N, 2) of camera-frame points ``p`` (N, 3), d(u, v) / d(x, y, z) (N, 2, 3) and
    whether each is in front (z over ``MIN_Z_M``; NaN rows where not), under intrinsics ``K``
    and the 12 coefficients ``d`` (``padded``)."""
    n = p.shape[0]
    uv = np.full((n, 2), np.nan)
    duv_dq = np.full((n, 2, 3), np.nan)
    in_front = np.empty(n, np.bool_)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for i in range(n):
        X, Y, Z = p[i, 0], p[i, 1], p[i, 2]
        in_front[i] = Z > MIN_Z_M
        if not in_front[i]:
            continue
        iz = 1.0 / Z
        x, y = X * iz, Y * iz
        xd, yd, a, b, c, e = _distorted(x, y, d)
        uv[i, 0] = fx * xd + cx
        uv[i, 1] = fy * yd + cy
        # (x, y) = (X, Y) / Z: d/dX = (iz, 0), d/dY = (0, iz), d/dZ = (-x iz, -y iz)
        duv_dq[i, 0, 0] = fx * a * iz
        duv_dq[i, 0, 1] = fx * b * iz
        duv_dq[i, 0, 2] = -fx * (a * x + b * y) * iz
        duv_dq[i, 1, 0] = fy * c * iz
        duv_dq[i, 1, 1] = fy * e * iz
        duv_dq[i, 1, 2] = -fy * (c * x + e * y) * iz
    return uv, duv_dq, in_front


@compiled
def undistorted(uv: Array, K: Array, d: Array) -> Array:
    """Normalised points (N, 2) whose projection is ``uv`` (N, 2): Newton from the distorted
    point on the distortion's own Jacobian (NaN where it finds none)."""
    out = np.empty((uv.shape[0], 2))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for i in range(uv.shape[0]):
        x0 = (uv[i, 0] - cx) / fx
        y0 = (uv[i, 1] - cy) / fy
        x, y = x0, y0
        done = False
        for _ in range(_MAX_NEWTON):
            xd, yd, a, b, c, e = _distorted(x, y, d)
            det = a * e - b * c
            if det == 0.0 or not math.isfinite(det):
                break
            fx_, fy_ = xd - x0, yd - y0
            step_x = (e * fx_ - b * fy_) / det
            step_y = (a * fy_ - c * fx_) / det
            x -= step_x
            y -= step_y
            if abs(step_x) + abs(step_y) < _STEP_DONE * (1.0 + abs(x) + abs(y)):
                done = True
                break
        if not done:
            # the last steps may dither at the rounding of the distortion: accept a point
            # that reprojects within 1e-12 of the target
            xd, yd, _, _, _, _ = _distorted(x, y, d)
            done = abs(xd - x0) + abs(yd - y0) < 1e-12
        out[i, 0] = x if done else np.nan
        out[i, 1] = y if done else np.nan
    return out
