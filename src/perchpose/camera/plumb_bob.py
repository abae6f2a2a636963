"""OpenCV's standard lens model (``plumb_bob``: radial k1-k6 as a ratio, tangential p1, p2,
thin prism s1-s4), compiled: the projection with its Jacobian, and its inverse.

``CameraModel`` used ``cv2.projectPoints`` and ``cv2.undistortPoints`` for it: a few corners at
a time, most of their cost was the call itself (tens of microseconds), several times a frame.
These give OpenCV's answers (projection to 1e-10 px, the inverse to the same convergence) for
4, 5, 8, 12 and 14 coefficients (the last two a tilted sensor's angles tau_x, tau_y: the
distorted point goes through the homography of OpenCV's ``computeTiltProjectionMatrix``).
Like OpenCV, the projection uses fx, fy, cx and cy of K and not its skew.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from perchpose.numeric.jit import compiled
from perchpose.numeric.linalg import times

Array = NDArray[np.float64]

# the coefficient counts OpenCV's model takes (padded with zeros to 14); 14 has a tilt
LENGTHS = (4, 5, 8, 12, 14)
# a point this close to the camera's plane (z, m) or behind it does not project
MIN_Z_M = 1e-9
# the inverse's Newton steps end below this (normalised units) or after this many
_STEP_DONE = 1e-15
_MAX_NEWTON = 50


def padded(dist: Array) -> Array:
    """``dist`` (4, 5, 8, 12 or 14 coefficients, OpenCV's order) as 14: k1, k2, p1, p2, k3,
    k4, k5, k6, s1, s2, s3, s4, tau_x, tau_y."""
    out = np.zeros(14)
    out[: dist.size] = dist
    return out


@compiled
def tilt_homography(tau_x: float, tau_y: float) -> Array:
    """The homography (3, 3) a sensor tilted by ``tau_x`` about x, then ``tau_y`` about y
    (rad), puts between the distorted normalised point and the image: the rotation
    R = R_y R_x, then the projection back onto the plane z = 1 along the optical axis,
    ``[[R22, 0, -R02], [0, R22, -R12], [0, 0, 1]] R``."""
    cx, sx, cy, sy = math.cos(tau_x), math.sin(tau_x), math.cos(tau_y), math.sin(tau_y)
    R = np.array(
        [
            [cy, sy * sx, -sy * cx],
            [0.0, cx, sx],
            [sy, -cy * sx, cy * cx],
        ]
    )
    P = np.array([[R[2, 2], 0.0, -R[0, 2]], [0.0, R[2, 2], -R[1, 2]], [0.0, 0.0, 1.0]])
    return times(P, R)


@compiled
def _inverse_3x3(H: Array) -> Array:
    """The inverse of a 3 x 3 matrix (by its adjugate)."""
    adj = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            r0, r1 = (j + 1) % 3, (j + 2) % 3
            c0, c1 = (i + 1) % 3, (i + 2) % 3
            adj[i, j] = H[r0, c0] * H[r1, c1] - H[r0, c1] * H[r1, c0]
    det = H[0, 0] * adj[0, 0] + H[0, 1] * adj[1, 0] + H[0, 2] * adj[2, 0]
    out: Array = adj / det
    return out


@compiled
def _tilted(H: Array, xd: float, yd: float) -> tuple[float, float, float, float, float, float]:
    """(``xd``, ``yd``) through the tilt's homography ``H``, and that map's Jacobian
    (d x/d xd, d x/d yd, d y/d xd, d y/d yd)."""
    w = H[2, 0] * xd + H[2, 1] * yd + H[2, 2]
    inv = 1.0 / w if w != 0.0 else 1.0
    x = (H[0, 0] * xd + H[0, 1] * yd + H[0, 2]) * inv
    y = (H[1, 0] * xd + H[1, 1] * yd + H[1, 2]) * inv
    return (
        x,
        y,
        (H[0, 0] - x * H[2, 0]) * inv,
        (H[0, 1] - x * H[2, 1]) * inv,
        (H[1, 0] - y * H[2, 0]) * inv,
        (H[1, 1] - y * H[2, 1]) * inv,
    )


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
    and the 14 coefficients ``d`` (``padded``)."""
    n = p.shape[0]
    uv = np.full((n, 2), np.nan)
    duv_dq = np.full((n, 2, 3), np.nan)
    in_front = np.empty(n, np.bool_)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tilted = d[12] != 0.0 or d[13] != 0.0
    H = tilt_homography(d[12], d[13])
    for i in range(n):
        X, Y, Z = p[i, 0], p[i, 1], p[i, 2]
        in_front[i] = Z > MIN_Z_M
        if not in_front[i]:
            continue
        iz = 1.0 / Z
        x, y = X * iz, Y * iz
        xd, yd, a, b, c, e = _distorted(x, y, d)
        if tilted:
            xd, yd, ta, tb, tc, te = _tilted(H, xd, yd)
            a, b, c, e = ta * a + tb * c, ta * b + tb * e, tc * a + te * c, tc * b + te * e
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
    tilted = d[12] != 0.0 or d[13] != 0.0
    untilt = _inverse_3x3(tilt_homography(d[12], d[13]))
    for i in range(uv.shape[0]):
        x0 = (uv[i, 0] - cx) / fx
        y0 = (uv[i, 1] - cy) / fy
        if tilted:  # the distorted point before the tilt's homography
            x0, y0, _, _, _, _ = _tilted(untilt, x0, y0)
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
