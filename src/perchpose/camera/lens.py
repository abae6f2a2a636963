"""The lens models in compiled code: OpenCV's fisheye (equidistant) projection, its Jacobian and
inverse, and ``lens_project`` / ``lens_normalize`` / ``lens_project_rigid_with_jacobian``, which
pick the model by its ``kind`` (``EQUIDISTANT`` or ``PLUMB_BOB``) as ``CameraModel.compiled_lens``
gives it."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import plumb_bob
from perchpose.numeric.jit import compiled

Array = NDArray[np.float64]


# The equidistant (fisheye) model's projection and its inverse, point by point.
_EQUIDISTANT_MAX_THETA_RAD = math.radians(110.0)


@compiled
def _equidistant_project(p: Array, K: Array, dist: Array) -> tuple[Array, NDArray[np.bool_]]:
    """Pixels (N, 2) of camera-frame points ``p`` (N, 3) under intrinsics ``K`` and the
    equidistant model's ``dist`` (k1..k4), and whether each projects one-to-one: within 110 deg
    of the axis, where the polynomial still rises."""
    k1, k2, k3, k4 = dist[0], dist[1], dist[2], dist[3]
    n = p.shape[0]
    uv = np.empty((n, 2))
    in_front = np.empty(n, np.bool_)
    for i in range(n):
        r_xy = math.hypot(p[i, 0], p[i, 1])
        theta = math.atan2(r_xy, p[i, 2])
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        scale = theta_d / r_xy if r_xy > 1e-15 else 1.0
        x, y = p[i, 0] * scale, p[i, 1] * scale
        uv[i, 0] = K[0, 0] * x + K[0, 1] * y + K[0, 2]
        uv[i, 1] = K[1, 1] * y + K[1, 2]
        rising = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        in_front[i] = theta < _EQUIDISTANT_MAX_THETA_RAD and rising > 0.0
    return uv, in_front


@compiled
def equidistant_project_with_jacobian(
    p: Array, K: Array, dist: Array
) -> tuple[Array, Array, NDArray[np.bool_]]:
    """``_equidistant_project`` and d(u, v) / d(x, y, z) (N, 2, 3) of each point."""
    uv, in_front = _equidistant_project(p, K, dist)
    k1, k2, k3, k4 = dist[0], dist[1], dist[2], dist[3]
    duv_dq = np.zeros((p.shape[0], 2, 3))
    for i in range(p.shape[0]):
        X, Y, Z = p[i, 0], p[i, 1], p[i, 2]
        r2 = X * X + Y * Y
        r = math.sqrt(r2)
        # d(x, y)/d(X, Y, Z) of the distorted normalised coordinates (x, y) = s (X, Y)
        if r < 1e-12 * max(abs(Z), 1e-300):  # on the axis: the pinhole's, 1 / Z
            dxy = np.array([[1.0 / Z, 0.0, 0.0], [0.0, 1.0 / Z, 0.0]])
        else:
            theta = math.atan2(r, Z)
            t2 = theta * theta
            theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
            rising = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            rho2 = r2 + Z * Z
            # d theta / d(X, Y, Z), then d s / d(X, Y, Z) with s = theta_d / r
            dtheta = (Z * X / (r * rho2), Z * Y / (r * rho2), -r / rho2)
            s = theta_d / r
            ds_dr = -theta_d / r2  # through r, at a fixed theta
            ds = (
                rising * dtheta[0] / r + ds_dr * X / r,
                rising * dtheta[1] / r + ds_dr * Y / r,
                rising * dtheta[2] / r,
            )
            dxy = np.empty((2, 3))
            for j in range(3):
                dxy[0, j] = X * ds[j]
                dxy[1, j] = Y * ds[j]
            dxy[0, 0] += s
            dxy[1, 1] += s
        for j in range(3):
            duv_dq[i, 0, j] = K[0, 0] * dxy[0, j] + K[0, 1] * dxy[1, j]
            duv_dq[i, 1, j] = K[1, 1] * dxy[1, j]
    return uv, duv_dq, in_front


@compiled
def equidistant_rays(uv: Array, K: Array, dist: Array) -> Array:
    """Unit rays (N, 3) of pixels ``uv`` (N, 2) under the equidistant model (Newton on the
    angle from the axis; also beyond 90 deg)."""
    k1, k2, k3, k4 = dist[0], dist[1], dist[2], dist[3]
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    rays = np.empty((uv.shape[0], 3))
    for i in range(uv.shape[0]):
        y = (uv[i, 1] - cy) / fy
        x = (uv[i, 0] - cx - skew * y) / fx
        theta_d = math.hypot(x, y)
        theta = theta_d
        for _ in range(20):  # Newton on theta * (1 + k1 t^2 + ...) = theta_d
            t2 = theta * theta
            f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
            df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            step = f / (df if abs(df) >= 1e-9 else 1e-9)
            theta -= step
            if not abs(step) > 1e-13:  # converged (a NaN step stops it too)
                break
        phi = math.atan2(y, x)
        s = math.sin(theta)
        rays[i, 0], rays[i, 1], rays[i, 2] = s * math.cos(phi), s * math.sin(phi), math.cos(theta)
    return rays


@compiled
def _on_plane(rays: Array) -> Array:
    """Rays (N, 3) on the normalised plane z = 1: (x/z, y/z); a ray within 1e-12 of z = 0
    is divided by 1e-12 instead."""
    out = np.empty((rays.shape[0], 2))
    for i in range(rays.shape[0]):
        z = rays[i, 2]
        if abs(z) < 1e-12:
            z = 1e-12
        out[i, 0] = rays[i, 0] / z
        out[i, 1] = rays[i, 1] / z
    return out


@compiled
def _equidistant_normalized(uv: Array, K: Array, dist: Array) -> Array:
    """``CameraModel.normalize`` of pixels ``uv`` (N, 2) under the equidistant model."""
    return _on_plane(equidistant_rays(uv, K, dist))


# the lens models of ``lens_project`` and ``lens_normalize``
EQUIDISTANT, PLUMB_BOB = 0, 1


class Lens(NamedTuple):
    """A lens as compiled code takes it (``CameraModel.compiled_lens``): its ``kind``
    (``EQUIDISTANT`` or ``PLUMB_BOB``), the intrinsics ``K`` (3, 3) and the ``coefficients``
    (the equidistant model's 4, or plumb_bob's padded to 14, ``plumb_bob.padded``)."""

    kind: int
    K: Array
    coefficients: Array


@compiled
def lens_project(kind: int, p: Array, K: Array, d: Array) -> tuple[Array, NDArray[np.bool_]]:
    """``CameraModel.project`` in compiled code, for the lens of ``compiled_lens``: pixels
    (N, 2) of camera-frame points ``p`` (N, 3) and whether each projects."""
    if kind == EQUIDISTANT:
        return _equidistant_project(p, K, d)
    uv, _, in_front = plumb_bob.project_with_jacobian(p, K, d)
    return uv, in_front


@compiled
def lens_project_rigid_with_jacobian(
    lens: Lens, p: Array, R: Array, t: Array
) -> tuple[Array, Array, Array, NDArray[np.bool_]]:
    """``CameraModel.project_rigid_with_jacobian`` in compiled code, for the lens of
    ``compiled_lens``."""
    kind, K, d = lens
    s = np.empty_like(p)
    q = np.empty_like(p)
    for i in range(p.shape[0]):
        for j in range(3):
            s[i, j] = R[j, 0] * p[i, 0] + R[j, 1] * p[i, 1] + R[j, 2] * p[i, 2]
            q[i, j] = s[i, j] + t[j]
    if kind == EQUIDISTANT:
        uv, duv_dq, in_front = equidistant_project_with_jacobian(q, K, d)
    else:
        uv, duv_dq, in_front = plumb_bob.project_with_jacobian(q, K, d)
    return uv, duv_dq, s, in_front


@compiled
def lens_normalize(kind: int, uv: Array, K: Array, d: Array) -> Array:
    """``CameraModel.normalize`` in compiled code, for the lens of ``compiled_lens``."""
    if kind == EQUIDISTANT:
        return _equidistant_normalized(uv, K, d)
    return plumb_bob.undistorted(uv, K, d)


@compiled
def all_within(points: Array, low: float, high_x: float, high_y: float) -> bool:
    """Whether every point (N, 2) has ``low <= x <= high_x`` and ``low <= y <= high_y``
    (False for a NaN)."""
    for i in range(points.shape[0]):
        x, y = points[i, 0], points[i, 1]
        if not (low <= x <= high_x and low <= y <= high_y):
            return False
    return True
