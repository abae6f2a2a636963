"""Linear algebra on small matrices (a pose's 6 x 6, a filter's 8 x 8, a frame's 16 corners),
compiled. numba's own ``np.linalg`` and matrix product call into scipy's LAPACK and BLAS, which
a plain install does not bring; and from Python each numpy call on such a matrix costs more to
set up than to compute. These are plain loops, called from other compiled code or once per
result from Python.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from perchpose.numeric.jit import compiled

Array = NDArray[np.float64]

# Jacobi sweeps after which the eigenvalues are taken as found (a 6 x 6 matrix needs 5-8)
_JACOBI_SWEEPS = 50


@compiled
def solve_in_place(A: Array, rhs: Array) -> bool:
    """Solves ``A x = rhs`` in place (``rhs`` becomes x; ``A`` is overwritten) by Gaussian
    elimination with partial pivoting; False where A is singular (a zero or NaN pivot)."""
    n = rhs.shape[0]
    for col in range(n):
        pivot, best = -1, 0.0
        for row in range(col, n):
            if abs(A[row, col]) > best:
                pivot, best = row, abs(A[row, col])
        if pivot < 0:
            return False
        if pivot != col:
            for j in range(n):
                A[col, j], A[pivot, j] = A[pivot, j], A[col, j]
            rhs[col], rhs[pivot] = rhs[pivot], rhs[col]
        for row in range(col + 1, n):
            f = A[row, col] / A[col, col]
            if f != 0.0:
                for j in range(col, n):
                    A[row, j] -= f * A[col, j]
                rhs[row] -= f * rhs[col]
    for col in range(n - 1, -1, -1):
        s = rhs[col]
        for j in range(col + 1, n):
            s -= A[col, j] * rhs[j]
        rhs[col] = s / A[col, col]
    return True


@compiled
def times(A: Array, B: Array) -> Array:
    """``A B``."""
    out = np.zeros((A.shape[0], B.shape[1]))
    for i in range(A.shape[0]):
        for k in range(A.shape[1]):
            a = A[i, k]
            if a != 0.0:
                for j in range(B.shape[1]):
                    out[i, j] += a * B[k, j]
    return out


@compiled
def times_transposed(A: Array, B: Array) -> Array:
    """``A B^T``."""
    return times(A, B.T)


@compiled
def transposed_times(A: Array, B: Array) -> Array:
    """``A^T B``."""
    return times(A.T, B)


@compiled
def inverted(A: Array) -> tuple[bool, Array]:
    """(whether A is invertible, ``A^-1``) by Gaussian elimination with partial pivoting, one
    column of the identity at a time."""
    n = A.shape[0]
    out = np.empty((n, n))
    for j in range(n):
        column = np.zeros(n)
        column[j] = 1.0
        if not solve_in_place(A.copy(), column):
            return False, out
        out[:, j] = column
    return True, out


@compiled
def symmetric_eigenvalues(A: Array) -> Array:
    """The eigenvalues of the symmetric matrix ``A``, ascending, by cyclic Jacobi rotations
    (accurate to the matrix's rounding relative to its largest entries)."""
    n = A.shape[0]
    M = A.copy()
    for _ in range(_JACOBI_SWEEPS):
        off = 0.0
        scale = 0.0
        for i in range(n):
            scale += M[i, i] * M[i, i]
            for j in range(i + 1, n):
                off += M[i, j] * M[i, j]
        if off <= 1e-30 * scale:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                if M[p, q] != 0.0:
                    _rotate(M, p, q)
    values = np.empty(n)
    for i in range(n):
        values[i] = M[i, i]
    return np.sort(values)


@compiled
def _rotate(M: Array, p: int, q: int) -> None:
    """One Jacobi rotation of the symmetric ``M`` in place, zeroing ``M[p, q]``."""
    theta = (M[q, q] - M[p, p]) / (2.0 * M[p, q])
    t = math.copysign(1.0, theta) / (abs(theta) + math.sqrt(theta * theta + 1.0))
    c = 1.0 / math.sqrt(t * t + 1.0)
    s = t * c
    for k in range(M.shape[0]):  # columns p and q
        m_kp, m_kq = M[k, p], M[k, q]
        M[k, p] = c * m_kp - s * m_kq
        M[k, q] = s * m_kp + c * m_kq
    for k in range(M.shape[0]):  # rows p and q
        m_pk, m_qk = M[p, k], M[q, k]
        M[p, k] = c * m_pk - s * m_qk
        M[q, k] = s * m_pk + c * m_qk


@compiled
def sandwiched(A: Array, B: Array) -> Array:
    """``A B A^T``: a covariance ``B`` carried through the linear map ``A``."""
    return times_transposed(times(A, B), A)


@compiled
def homography_of_4(src: Array, dst: Array) -> tuple[bool, Array]:
    """(whether one exists, the homography H (3, 3), h33 = 1) taking the 4 points ``src``
    (4, 2) to ``dst`` (4, 2) exactly: the 8 x 8 linear system of the direct linear
    transform."""
    A = np.zeros((8, 8))
    rhs = np.empty(8)
    for k in range(4):
        x, y, u, v = src[k, 0], src[k, 1], dst[k, 0], dst[k, 1]
        A[2 * k, 0], A[2 * k, 1], A[2 * k, 2] = x, y, 1.0
        A[2 * k, 6], A[2 * k, 7] = -u * x, -u * y
        A[2 * k + 1, 3], A[2 * k + 1, 4], A[2 * k + 1, 5] = x, y, 1.0
        A[2 * k + 1, 6], A[2 * k + 1, 7] = -v * x, -v * y
        rhs[2 * k], rhs[2 * k + 1] = u, v
    H = np.ones((3, 3))
    if not solve_in_place(A, rhs):
        return False, H
    for i in range(8):
        H[i // 3, i % 3] = rhs[i]
    return True, H


@compiled
def through_homography(H: Array, points: Array) -> Array:
    """``points`` (N, 2) through the homography ``H`` (3, 3) (NaN where one maps to
    infinity)."""
    out = np.empty((points.shape[0], 2))
    for i in range(points.shape[0]):
        x, y = points[i, 0], points[i, 1]
        w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
        if w == 0.0:
            out[i, 0] = out[i, 1] = np.nan
            continue
        out[i, 0] = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w
        out[i, 1] = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w
    return out
