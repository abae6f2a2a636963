"""The constant-velocity Kalman filter's matrix arithmetic, compiled.

The state is four (value, rate) pairs, ``[psi, psi_dot, tx, tx_dot, ty, ty_dot, tz, tz_dot]``,
and the measurement picks the values (even indices). Both structures are used directly: the
transition adds ``dt`` times each rate to its value, and ``H P`` is P's even rows. Each step is
a few hundred multiply-adds on 8 x 8 matrices, which numpy spends tens of microseconds setting
up; ``perchpose.filters.kalman`` holds the filter and calls these (yaw wrapping stays there).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from perchpose.numeric.jit import compiled
from perchpose.numeric.linalg import solve_in_place, times, times_transposed

Array = NDArray[np.float64]

N_STATE = 8
N_MEASURED = 4


@compiled
def propagated_state(x: Array, dt_s: float) -> Array:
    """``F x``: each value moved on by ``dt_s`` times its rate."""
    out = x.copy()
    for k in range(0, N_STATE, 2):
        out[k] += dt_s * x[k + 1]
    return out


@compiled
def propagated_covariance(P: Array, dt_s: float, Q: Array) -> Array:
    """``F P F^T + Q`` for a step of ``dt_s`` seconds."""
    FP = P.copy()
    for k in range(0, N_STATE, 2):
        for j in range(N_STATE):
            FP[k, j] += dt_s * P[k + 1, j]
    out = FP.copy()
    for i in range(N_STATE):
        for k in range(0, N_STATE, 2):
            out[i, k] += dt_s * FP[i, k + 1]
    for i in range(N_STATE):
        for j in range(N_STATE):
            out[i, j] += Q[i, j]
    return out


@compiled
def innovation_covariance(P: Array, R: Array) -> Array:
    """``S = H P H^T + R`` (4, 4)."""
    S = R.copy()
    for i in range(N_MEASURED):
        for j in range(N_MEASURED):
            S[i, j] += P[2 * i, 2 * j]
    return S


@compiled
def gain(P: Array, S: Array) -> tuple[bool, Array]:
    """(solved, the gain ``K = P H^T S^-1`` (8, 4)); not solved where S is singular."""
    K = np.empty((N_STATE, N_MEASURED))
    for j in range(N_STATE):
        # row j of K solves S k = (H P)[:, j] (S symmetric)
        A = S.copy()
        rhs = np.empty(N_MEASURED)
        for i in range(N_MEASURED):
            rhs[i] = P[2 * i, j]
        if not solve_in_place(A, rhs):
            return False, K
        for i in range(N_MEASURED):
            K[j, i] = rhs[i]
    return True, K


@compiled
def mahalanobis2(y: Array, S: Array) -> float:
    """``y^T S^-1 y``; inf where S is singular."""
    A = S.copy()
    v = y.copy()
    if not solve_in_place(A, v):
        return np.inf
    total = 0.0
    for i in range(y.shape[0]):
        total += y[i] * v[i]
    return total


@compiled
def corrected_state(x: Array, K: Array, y: Array) -> Array:
    """``x + K y``."""
    out = x.copy()
    for i in range(N_STATE):
        for j in range(N_MEASURED):
            out[i] += K[i, j] * y[j]
    return out


@compiled
def joseph_covariance(P: Array, K: Array, R: Array) -> Array:
    """``(I - K H) P (I - K H)^T + K R K^T``: the corrected covariance in the Joseph form,
    which stays symmetric and positive definite."""
    A = np.eye(N_STATE)  # I - K H
    for i in range(N_STATE):
        for j in range(N_MEASURED):
            A[i, 2 * j] -= K[i, j]
    return times_transposed(times(A, P), A) + times_transposed(times(K, R), K)
