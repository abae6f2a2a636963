"""Compiled refinement of a pose from points and their normalised image coordinates.

``refine_pose`` does what OpenCV's ``solvePnPRefineLM`` does with an identity camera matrix:
it moves a pose to the least squares of the reprojection errors in normalised coordinates
(x/z, y/z). It runs compiled (``jit.compiled``): a marker's four corners take a few
microseconds, where a call of OpenCV's costs tens of them in argument handling alone, and
every marker pose of every frame makes two (one per IPPE solution).

Parametrisation: ``R' = exp([w]x) R``, ``t' = t + dt`` with ``(w, dt)`` as in
``pose.joint``; Levenberg-Marquardt with the damping on the normal matrix's diagonal. The
projected points' Jacobian over (w, dt) (``pose_rows``) and the weighted normal equations
(``normal_equations``) are the joint pose's too, through the lens model there.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from perchpose.numeric.jit import compiled
from perchpose.numeric.linalg import solve_in_place, times

Array = NDArray[np.float64]

# The refinement ends when a step moves no entry of (w, dt) by more than this (rad, m): a
# nanometre, far below what a marker's pose is ever known to (tens of micrometres at best);
# OpenCV's ends at FLT_EPSILON (1.2e-7) relative. With noise in the corners the steps shrink
# linearly, each a fraction of the one before: from IPPE's solutions on the default approach,
# 8.6 rounds on average to this tolerance against 15.7 to 1e-12, for poses under 1e-10 m
# apart.
STEP_TOLERANCE = 1e-9
MAX_ITERATIONS = 40


@compiled
def rotation_of(w0: float, w1: float, w2: float) -> Array:
    """``exp([w]x)`` (3, 3) of the rotation vector ``w`` (Rodrigues' formula)."""
    theta = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    R = np.eye(3)
    if theta < 1e-300:
        return R
    if theta < 1e-4:
        a, b = 1.0 - theta * theta / 6.0, 0.5 - theta * theta / 24.0
    else:
        a, b = math.sin(theta) / theta, (1.0 - math.cos(theta)) / (theta * theta)
    K = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    for i in range(3):
        for j in range(3):
            KK = K[i, 0] * K[0, j] + K[i, 1] * K[1, j] + K[i, 2] * K[2, j]
            R[i, j] += a * K[i, j] + b * KK
    return R


@compiled
def turned(w: Array, R: Array) -> Array:
    """``exp([w]x) R``: the rotation ``R`` (3, 3) turned by the small rotation ``w`` (3,)
    about the axes of its left frame."""
    return times(rotation_of(w[0], w[1], w[2]), R)


@compiled
def pose_rows(s: Array, duv_dq: Array) -> Array:
    """The Jacobian (2N, 6) of N projected points over (w, dt), from the rotated points
    ``s = R p`` (N, 3) and the projection's d(u, v) / d(x, y, z) (N, 2, 3): a point moves by
    ``dq = -[s]x w + dt``."""
    J = np.empty((2 * s.shape[0], 6))
    for i in range(s.shape[0]):
        s0, s1, s2 = s[i, 0], s[i, 1], s[i, 2]
        for axis in range(2):
            a0, a1, a2 = duv_dq[i, axis, 0], duv_dq[i, axis, 1], duv_dq[i, axis, 2]
            row = 2 * i + axis
            J[row, 0] = -a1 * s2 + a2 * s1
            J[row, 1] = a0 * s2 - a2 * s0
            J[row, 2] = -a0 * s1 + a1 * s0
            J[row, 3], J[row, 4], J[row, 5] = a0, a1, a2
    return J


@compiled
def normal_equations(J: Array, w: Array, r: Array) -> tuple[Array, Array]:
    """``J^T W J`` (6, 6) and ``J^T W r`` (6,) for residuals ``r`` (M,) with Jacobian ``J``
    (M, 6) and weights ``w`` (M,)."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    for i in range(J.shape[0]):
        for j in range(6):
            wj = w[i] * J[i, j]
            g[j] += wj * r[i]
            for k in range(j, 6):
                H[j, k] += wj * J[i, k]
    for j in range(6):
        for k in range(j):
            H[j, k] = H[k, j]
    return H, g


@compiled
def _cost_and_normal_equations(
    points_m: Array, xy: Array, R: Array, t: Array
) -> tuple[float, Array, Array]:
    """The sum of squared normalised reprojection errors at (R, t), and their normal
    equations over (w, dt) (``normal_equations``); an infinite cost where a point is not in
    front of the camera."""
    n = points_m.shape[0]
    s = np.empty((n, 3))
    duv_dq = np.zeros((n, 2, 3))
    r = np.empty(2 * n)
    for i in range(n):
        for k in range(3):
            s[i, k] = R[k, 0] * points_m[i, 0] + R[k, 1] * points_m[i, 1] + R[k, 2] * points_m[i, 2]
        z = s[i, 2] + t[2]
        if not z > 1e-12:
            return math.inf, np.zeros((6, 6)), np.zeros(6)
        x, y = (s[i, 0] + t[0]) / z, (s[i, 1] + t[1]) / z
        r[2 * i], r[2 * i + 1] = x - xy[i, 0], y - xy[i, 1]
        # the pinhole's d(x, y)/d(q) at q = s + t
        duv_dq[i, 0, 0], duv_dq[i, 0, 2] = 1.0 / z, -x / z
        duv_dq[i, 1, 1], duv_dq[i, 1, 2] = 1.0 / z, -y / z
    H, g = normal_equations(pose_rows(s, duv_dq), np.ones(2 * n), r)
    return float(np.sum(r * r)), H, g


@compiled
def refine_pose(points_m: Array, xy: Array, R0: Array, t0: Array) -> tuple[Array, Array, bool]:
    """The pose (R (3, 3), t (3,)) nearest ``(R0, t0)`` that minimises the squared
    normalised reprojection errors of ``points_m`` (N, 3, object frame) against ``xy``
    (N, 2); and whether it is one (False where the start puts a point behind the camera or
    the normal equations are singular: then the start is returned)."""
    R, t = R0.copy(), t0.copy()
    cost, H, g = _cost_and_normal_equations(points_m, xy, R, t)
    if not math.isfinite(cost):
        return R, t, False
    damping = 1e-6
    for _ in range(MAX_ITERATIONS):
        A = H.copy()
        for j in range(6):
            A[j, j] += damping * A[j, j]
        step = -g
        if not solve_in_place(A, step):
            return R0.copy(), t0.copy(), False
        R_try = turned(step[:3], R)
        t_try = t + step[3:]
        cost_try, H_try, g_try = _cost_and_normal_equations(points_m, xy, R_try, t_try)
        largest = np.max(np.abs(step))
        if cost_try <= cost:
            R, t, cost, H, g = R_try, t_try, cost_try, H_try, g_try
            damping = max(damping * 0.1, 1e-12)
            if largest < STEP_TOLERANCE:
                break
        else:
            if largest < STEP_TOLERANCE:
                break
            damping *= 10.0
    return R, t, True
