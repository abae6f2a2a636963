"""Compiled refinement of a pose from points and their normalised image coordinates.

``refine_pose`` does what OpenCV's ``solvePnPRefineLM`` does with an identity camera matrix:
it moves a pose to the least squares of the reprojection errors in normalised coordinates
(x/z, y/z). It runs compiled (``jit.compiled``): a marker's four corners take a few
microseconds, where a call of OpenCV's costs tens of them in argument handling alone, and
every marker pose of every frame makes two (one per IPPE solution).

Parametrisation: ``R' = exp([w]x) R``, ``t' = t + dt`` with ``(w, dt)`` as in
``joint_pose``; Levenberg-Marquardt with the damping on the normal matrix's diagonal.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from perchpose.jit import compiled
from perchpose.step_model import solve_in_place

Array = NDArray[np.float64]

# The refinement ends when a step moves no entry of (w, dt) by more than this (rad, m);
# OpenCV's ends at FLT_EPSILON (1.2e-7) relative.
STEP_TOLERANCE = 1e-12
MAX_ITERATIONS = 40


@compiled
def _rotation_of(w0: float, w1: float, w2: float) -> Array:
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
def _turned(A: Array, R: Array) -> Array:
    """``A @ R`` of two (3, 3) matrices (a loop: numba's matrix product needs scipy's
    BLAS)."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * R[0, j] + A[i, 1] * R[1, j] + A[i, 2] * R[2, j]
    return out


@compiled
def turned(w: Array, R: Array) -> Array:
    """``exp([w]x) R``: the rotation ``R`` (3, 3) turned by the small rotation ``w`` (3,)
    about the axes of its left frame."""
    return _turned(_rotation_of(w[0], w[1], w[2]), R)


@compiled
def _cost_and_normal_equations(
    points_m: Array, xy: Array, R: Array, t: Array, H: Array, g: Array
) -> float:
    """The sum of squared normalised reprojection errors at (R, t), and the normal matrix
    ``H = J^T J`` and gradient ``g = J^T r`` over (w, dt) written in place; inf where a
    point is not in front of the camera."""
    H[:, :] = 0.0
    g[:] = 0.0
    cost = 0.0
    row = np.empty(6)
    for i in range(points_m.shape[0]):
        s0 = R[0, 0] * points_m[i, 0] + R[0, 1] * points_m[i, 1] + R[0, 2] * points_m[i, 2]
        s1 = R[1, 0] * points_m[i, 0] + R[1, 1] * points_m[i, 1] + R[1, 2] * points_m[i, 2]
        s2 = R[2, 0] * points_m[i, 0] + R[2, 1] * points_m[i, 1] + R[2, 2] * points_m[i, 2]
        q0, q1, q2 = s0 + t[0], s1 + t[1], s2 + t[2]
        if not q2 > 1e-12:
            return math.inf
        inv_z = 1.0 / q2
        x, y = q0 * inv_z, q1 * inv_z
        for axis in range(2):
            r = (x - xy[i, 0]) if axis == 0 else (y - xy[i, 1])
            # d(x or y)/dq, then dq/dw = -[s]x and dq/dt = I
            a0 = inv_z if axis == 0 else 0.0
            a1 = 0.0 if axis == 0 else inv_z
            a2 = -(x if axis == 0 else y) * inv_z
            row[0] = -a1 * s2 + a2 * s1
            row[1] = a0 * s2 - a2 * s0
            row[2] = -a0 * s1 + a1 * s0
            row[3], row[4], row[5] = a0, a1, a2
            cost += r * r
            for j in range(6):
                g[j] += row[j] * r
                for k in range(j, 6):
                    H[j, k] += row[j] * row[k]
    for j in range(6):
        for k in range(j):
            H[j, k] = H[k, j]
    return cost


@compiled
def refine_pose(points_m: Array, xy: Array, R0: Array, t0: Array) -> tuple[Array, Array, bool]:
    """The pose (R (3, 3), t (3,)) nearest ``(R0, t0)`` that minimises the squared
    normalised reprojection errors of ``points_m`` (N, 3, object frame) against ``xy``
    (N, 2); and whether it is one (False where the start puts a point behind the camera or
    the normal equations are singular: then the start is returned)."""
    R, t = R0.copy(), t0.copy()
    H, g = np.empty((6, 6)), np.empty(6)
    H_try, g_try = np.empty((6, 6)), np.empty(6)
    cost = _cost_and_normal_equations(points_m, xy, R, t, H, g)
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
        cost_try = _cost_and_normal_equations(points_m, xy, R_try, t_try, H_try, g_try)
        largest = np.max(np.abs(step))
        if cost_try <= cost:
            R, t, cost = R_try, t_try, cost_try
            H[:, :] = H_try
            g[:] = g_try
            damping = max(damping * 0.1, 1e-12)
            if largest < STEP_TOLERANCE:
                break
        else:
            if largest < STEP_TOLERANCE:
                break
            damping *= 10.0
    return R, t, True
