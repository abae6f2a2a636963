"""One pose from every visible corner of every marker, with its covariance and the bound.

The paper solves each marker alone and fuses the poses with fixed weights. Here all detected
corners (4 per marker, in the target frame) go into one least-squares PnP, and the pose's
6 x 6 covariance follows from the Jacobian of the corners' pixel positions: for independent
corner noise of ``sigma_px`` per axis, ``cov = sigma^2 (J^T J)^-1``. At the true pose the same
matrix is the Cramer-Rao bound: no unbiased estimator from those corners does better.

Pose perturbation: ``T(delta) = [exp([w]x) R, t + dt]`` with ``delta = (w, dt)``, ``w`` a small
rotation about the camera axes (rad) and ``dt`` the shift of the target centre (m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.camera.lens import Lens, lens_project_rigid_with_jacobian
from perchpose.geometry import make_transform
from perchpose.numeric.jit import compiled
from perchpose.numeric.linalg import (
    inverted,
    solve_in_place,
    symmetric_eigenvalues,
    times,
    times_transposed,
    transposed_times,
)
from perchpose.pose.refine import normal_equations, pose_rows, turned
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection

Array = NDArray[np.float64]
# The joint pose's Gauss-Newton ends once a step changes no entry of (w, dt) by this much
# (rad, m). With the corners' noise in the residuals it converges linearly, each step 0.02-0.3
# of the one before (fpv approach, default and harsh images), so what is left is under this
# again: a tenth of a micrometre, a thousandth of the pose's own standard deviation at best.
CONVERGED = 1e-7


@dataclass(frozen=True)
class PoseUncertainty:
    """Standard deviations of the estimate's components: target centre in the camera frame
    (m) and yaw (rad)."""

    x_m: float
    y_m: float
    z_m: float
    yaw_rad: float


@dataclass(frozen=True)
class JointPose:
    """T_camera_target from all corners; covariance (6, 6) over (w, dt) for the corner noise
    it was computed with; reproj_rms_px over all corners; markers used; corners_covariance
    (6, 6) over (w, dt) for the corners' own covariance where one was given
    (``sandwich_covariance``); misfit: then also the residuals' squared length in that
    covariance's metric, and what it would be on average were the covariance right
    (``corner_misfit``)."""

    T_camera_target: Array
    covariance: Array
    reproj_rms_px: float
    markers: tuple[int, ...]
    corners_covariance: Array | None = None
    misfit: tuple[float, float] = (math.nan, math.nan)

    @property
    def std(self) -> PoseUncertainty:
        return uncertainty(self.T_camera_target, self.covariance)


@compiled
def _gauss_newton_step(J: Array, w: Array, r: Array) -> tuple[Array, bool, float]:
    """The step (6,) over (w, dt) minimising ``sum w (r + J step)^2``, False where the
    normal equations are singular, and the step's largest entry (absolute)."""
    H, g = normal_equations(J, w, r)
    for j in range(6):
        H[j, j] += 1e-12
    step = -g
    solved = solve_in_place(H, step)
    return step, solved, np.max(np.abs(step))


def _project_with_jacobian(
    camera: CameraModel, R: Array, t: Array, points_target_m: Array
) -> tuple[Array, Array] | None:
    """Pixels (2N,) of the points under the pose (R, t), and their Jacobian (2N, 6) over
    (w, dt). None if a point does not project (behind the camera, or beyond the lens
    model's reach)."""
    in_front, uv_flat, J = _rows_compiled(camera.compiled_lens, points_target_m, R, t)
    return (uv_flat, J) if in_front else None


@compiled
def _rows_compiled(lens: Lens, points_m: Array, R: Array, t: Array) -> tuple[bool, Array, Array]:
    """``_project_with_jacobian`` through the lens of ``CameraModel.compiled_lens``: (whether
    every point projects, pixels (2N,), Jacobian (2N, 6))."""
    uv, duv_dq, s, in_front = lens_project_rigid_with_jacobian(lens, points_m, R, t)
    return bool(in_front.all()), uv.reshape(-1), pose_rows(s, duv_dq)


def _weights(sigma_px: float | Array, n_points: int) -> Array:
    sigma = np.broadcast_to(np.asarray(sigma_px, np.float64), (n_points,))
    return np.repeat(1.0 / sigma**2, 2)


def pose_covariance(
    camera: CameraModel, T: Array, points_target_m: Array, sigma_px: float | Array
) -> Array | None:
    """``(J^T W J)^-1`` with ``W = 1 / sigma^2`` at ``T`` for corners ``points_target_m``
    (N, 3) with pixel noise ``sigma_px`` per axis (one value, or one per corner), over
    (w, dt): the pose's covariance, and at the true pose the Cramer-Rao bound. None if
    degenerate or a corner is behind the camera."""
    return _covariances_at(camera, T, points_target_m, sigma_px)[0]


def sandwich_covariance(
    camera: CameraModel,
    T: Array,
    points_target_m: Array,
    sigma_px: float | Array,
    corner_covariance_px2: Array,
) -> Array | None:
    """The covariance over (w, dt) of the pose fitted at ``T`` to corners ``points_target_m``
    (N, 3) weighted by ``1 / sigma_px^2`` (one value, or one per corner) when their errors
    have the covariance ``corner_covariance_px2`` (2N, 2N; px^2, x0, y0, x1, ...):
    ``H^-1 J^T W S W J H^-1`` with ``H = J^T W J``. Where S is the weights' own iid noise
    this is ``pose_covariance``; where the corners' errors are correlated (neighbouring
    corners share a fitted side) it is what the weights' covariance gets wrong. None if
    degenerate or a corner is behind the camera."""
    return _covariances_at(camera, T, points_target_m, sigma_px, corner_covariance_px2)[1]


def _covariances_at(
    camera: CameraModel,
    T: Array,
    points_target_m: Array,
    sigma_px: float | Array,
    corner_covariance_px2: Array | None = None,
) -> tuple[Array | None, Array | None]:
    """``_covariances`` at the pose ``T``; both None where a corner does not project."""
    projected = _project_with_jacobian(camera, T[:3, :3], T[:3, 3], points_target_m)
    if projected is None:
        return None, None
    w = _weights(sigma_px, points_target_m.shape[0])
    return _covariances(projected[1], w, corner_covariance_px2)


def _covariances(
    J: Array, w: Array, corner_covariance_px2: Array | None = None
) -> tuple[Array | None, Array | None]:
    """Over (w, dt), from the corners' Jacobian (2N, 6) over (w, dt) and their weights: the
    weights' own covariance, and with ``corner_covariance_px2`` the sandwich
    (``sandwich_covariance``; else None). Both None if degenerate."""
    S = _NONE if corner_covariance_px2 is None else np.asarray(corner_covariance_px2, np.float64)
    solved, plain, own = _weighted_covariances(J, w, S)
    if not solved:
        return None, None
    return plain, None if corner_covariance_px2 is None else own


_NONE = np.zeros((0, 0))


@compiled
def _weighted(J: Array, w: Array) -> Array:
    """``W J``: each row of J times its weight."""
    Jw = np.empty_like(J)
    for i in range(J.shape[0]):
        for j in range(J.shape[1]):
            Jw[i, j] = w[i] * J[i, j]
    return Jw


@compiled
def _weighted_covariances(J: Array, w: Array, S: Array) -> tuple[bool, Array, Array]:
    """``_covariances``' arithmetic: (solved, ``(J^T W J)^-1``, the sandwich with ``S``, or
    an empty array where S is empty); not solved where ``J^T W J`` is too ill-conditioned
    to invert (its eigenvalues over 1e14 apart)."""
    Jw = _weighted(J, w)
    info = transposed_times(J, Jw)
    eigenvalues = symmetric_eigenvalues(info)
    if not eigenvalues[0] * 1e14 > eigenvalues[-1]:
        return False, info, _NONE
    solved, H_inv = inverted(info)
    if not solved:
        return False, info, _NONE
    plain = 0.5 * (H_inv + H_inv.T)
    if S.shape[0] == 0:
        return True, plain, _NONE
    B = times(Jw, H_inv)
    return True, plain, transposed_times(B, times(S, B))


def uncertainty(T: Array, covariance: Array) -> PoseUncertainty:
    """Standard deviations of x, y, z (m) and yaw (rad) for a covariance over (w, dt)."""
    J = measurement_jacobian(T)
    var = np.diag(J @ covariance @ J.T)
    return PoseUncertainty(
        *(math.sqrt(max(float(v), 0.0)) for v in (var[1], var[2], var[3], var[0]))
    )


def measurement_jacobian(T: Array) -> Array:
    """d(yaw, x, y, z) / d(w, dt): (4, 6), to carry a pose covariance to the estimate's
    components. With ``R' = (I + [w]x) R`` and ``yaw = atan2(R10, R00)``: d yaw / dw =
    ``(-R00 R20, -R10 R20, R00^2 + R10^2) / (R00^2 + R10^2)``."""
    R = T[:3, :3]
    J = np.zeros((4, 6))
    norm2 = float(R[0, 0] ** 2 + R[1, 0] ** 2)
    if norm2 > 0.0:  # else the yaw is not defined (the target seen edge on)
        J[0, 0] = -R[0, 0] * R[2, 0] / norm2
        J[0, 1] = -R[1, 0] * R[2, 0] / norm2
        J[0, 2] = 1.0
    J[1, 3] = J[2, 4] = J[3, 5] = 1.0
    return J


def target_points(target: TargetSpec, detections: tuple[MarkerDetection, ...]) -> Array:
    """The corners (4N, 3) in the target frame of the detected markers, detection order."""
    return np.concatenate([target.markers[d.marker_index].corners_target_m for d in detections])


def solve_joint_pose(
    camera: CameraModel,
    target: TargetSpec,
    detections: tuple[MarkerDetection, ...],
    T_initial: Array,
    sigma_px: float | Array,
    iterations: int = 6,
    corner_covariance_px2: Array | None = None,
) -> JointPose | None:
    """Least-squares pose from every corner of ``detections`` (pixel residuals through the
    lens model weighted by ``1 / sigma_px^2``, one value or one per detection; Gauss-Newton
    from ``T_initial``, e.g. the best single-marker pose). ``corner_covariance_px2`` (8N, 8N;
    px^2, detection order): the corners' own covariance, for ``corners_covariance``."""
    if not detections:
        return None
    points = target_points(target, detections)
    uv = np.concatenate([d.corners_px for d in detections]).reshape(-1)
    sigma = np.asarray(sigma_px, np.float64)
    if sigma.ndim == 0:
        sigma = np.full(len(detections), float(sigma))
    w = np.repeat(1.0 / sigma**2, 8)  # each detection's 4 corners, x and y
    T_start = np.asarray(T_initial, np.float64)
    R, t = np.ascontiguousarray(T_start[:3, :3]), T_start[:3, 3].copy()
    solved, R, t, pixels, J = _gauss_newton(camera.compiled_lens, R, t, points, uv, w, iterations)
    if not solved:
        return None
    projected = (pixels, J)
    cov, own = _covariances(J, w, corner_covariance_px2)
    if cov is None:
        return None
    residual = uv - projected[0]
    rms = math.sqrt(float(residual @ residual) / points.shape[0])
    T = make_transform(R, t)
    misfit = (
        (math.nan, math.nan)
        if corner_covariance_px2 is None
        else corner_misfit(projected[1], w, residual, corner_covariance_px2)
    )
    return JointPose(T, cov, rms, tuple(d.marker_index for d in detections), own, misfit)


@compiled
def _gauss_newton(
    lens: Lens,
    R: Array,
    t: Array,
    points_m: Array,
    uv: Array,
    w: Array,
    iterations: int,
) -> tuple[bool, Array, Array, Array, Array]:
    """``solve_joint_pose``'s Gauss-Newton from (R, t) through the lens of
    ``CameraModel.compiled_lens``: (whether it held: every point projects and the normal
    equations are solvable, R, t, the points' pixels (2N,) and their Jacobian (2N, 6) at the
    end)."""
    for _ in range(iterations):
        in_front, pixels, J = _rows_compiled(lens, points_m, R, t)
        if not in_front:
            return False, R, t, pixels, J
        r = pixels - uv
        delta, solved, largest = _gauss_newton_step(J, w, r)
        if not solved:
            return False, R, t, pixels, J
        R = turned(delta[:3], R)
        t = t + delta[3:]
        if largest < CONVERGED:
            # the last step is too small to change the Jacobian: the pixels after it from it
            for i in range(pixels.shape[0]):
                moved = 0.0
                for j in range(6):
                    moved += J[i, j] * delta[j]
                pixels[i] += moved
            return True, R, t, pixels, J
    in_front, pixels, J = _rows_compiled(lens, points_m, R, t)
    return in_front, R, t, pixels, J


def corner_misfit(J: Array, w: Array, residual: Array, S: Array) -> tuple[float, float]:
    """How well the corners' covariance ``S`` explains the fit's residuals: ``r^T S^-1 r``,
    and its expected value were S right, ``trace(S^-1 M S M^T)`` with ``M = I - J H^-1 J^T W``
    (the residuals of a fit weighted by ``w`` are M times the corners' errors). Their ratio
    is the a-posteriori variance factor: about 1 where S is right, over 1 where the corners
    err more than S says (blur, rolling shutter: errors the edge points' scatter misses).
    (nan, nan) where S is singular."""
    return _misfit(J, w, residual, np.asarray(S, np.float64))


@compiled
def _misfit(J: Array, w: Array, residual: Array, S: Array) -> tuple[float, float]:
    """``corner_misfit``'s arithmetic."""
    Jw = _weighted(J, w)
    solved, H_inv = inverted(transposed_times(J, Jw))
    invertible, S_inv = inverted(S)
    if not (solved and invertible):
        return math.nan, math.nan
    M = -times_transposed(times(J, H_inv), Jw)
    for i in range(M.shape[0]):
        M[i, i] += 1.0
    S_inv_r = times(S_inv, residual.reshape(-1, 1))
    observed = 0.0
    for i in range(residual.shape[0]):
        observed += residual[i] * S_inv_r[i, 0]
    # trace(S^-1 M S M^T) = sum over i, k of (S^-1 M)[i, k] (S M^T)[k, i]
    A = times(S_inv, M)
    C = times_transposed(S, M)
    expected = 0.0
    for i in range(A.shape[0]):
        for k in range(A.shape[1]):
            expected += A[i, k] * C[k, i]
    return observed, expected
