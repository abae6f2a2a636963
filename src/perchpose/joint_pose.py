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

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.camera import CameraModel
from perchpose.geometry import rvec_tvec_from_transform, transform_from_rvec_tvec, yaw_rad
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection

Array = NDArray[np.float64]
_STEP_RAD = 1e-6
_STEP_M = 1e-6
# The joint pose's Gauss-Newton ends once a step changes no entry of (rvec, tvec) by this much
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


def _perturbed(T: Array, delta: Array) -> Array:
    rot, _ = cv2.Rodrigues(np.asarray(delta[:3], np.float64).reshape(3, 1))
    out = T.copy()
    out[:3, :3] = np.asarray(rot, np.float64) @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + delta[3:]
    return out


def _project_with_jacobian(
    camera: CameraModel, rvec: Array, tvec: Array, points_target_m: Array
) -> tuple[Array, Array] | None:
    """Pixels (2N,) of the points under the pose (rvec, tvec), and their Jacobian (2N, 6)
    with respect to (rvec, tvec), from OpenCV's own projection (the same models as
    ``CameraModel.project``). None if a point is not in front of the camera."""
    R, _ = cv2.Rodrigues(rvec.reshape(3, 1))
    depth = (np.asarray(R, np.float64) @ points_target_m.T)[2] + tvec[2]
    if not np.all(depth > 1e-6):
        return None
    obj = points_target_m.reshape(-1, 1, 3)
    if camera.model == "equidistant":
        uv, jac = cv2.fisheye.projectPoints(
            obj,
            rvec.reshape(3, 1),
            tvec.reshape(3, 1),
            camera.K,
            camera.dist.reshape(4, 1),
            alpha=float(camera.K[0, 1] / camera.K[0, 0]),
        )
        J = np.asarray(jac, np.float64)[:, 8:14]  # fx fy cx cy k1-k4 | om (3) T (3) | alpha
    else:
        uv, jac = cv2.projectPoints(
            obj, rvec.reshape(3, 1), tvec.reshape(3, 1), camera.K, camera.dist
        )
        J = np.asarray(jac, np.float64)[:, :6]  # rvec (3) tvec (3) | f, c, distortion
    return np.asarray(uv, np.float64).reshape(-1), J


def _rotation_jacobian(rvec: Array) -> Array:
    """d(w)/d(rvec) (3, 3): how a change of the rotation vector turns the rotation, as a small
    rotation ``w`` about the camera axes (``exp([w]x) R``): the left Jacobian of SO(3),
    ``I + (1 - cos t) / t^2 [r]x + (t - sin t) / t^3 [r]x^2`` with ``t = |r|`` (its series
    near 0)."""
    r = np.asarray(rvec, np.float64).reshape(3)
    K = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    t = float(np.linalg.norm(r))
    if t < 1e-4:
        a, b = 0.5 - t * t / 24.0, 1.0 / 6.0 - t * t / 120.0
    else:
        a, b = (1.0 - math.cos(t)) / (t * t), (t - math.sin(t)) / (t * t * t)
    return np.asarray(np.eye(3) + a * K + b * (K @ K), np.float64)


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
    rvec3, tvec3 = rvec_tvec_from_transform(T)
    rvec, tvec = rvec3.reshape(3), tvec3.reshape(3)
    projected = _project_with_jacobian(camera, rvec, tvec, points_target_m)
    if projected is None:
        return None, None
    w = _weights(sigma_px, points_target_m.shape[0])
    return _covariances(projected[1], w, rvec, corner_covariance_px2)


def _covariances(
    J: Array, w: Array, rvec: Array, corner_covariance_px2: Array | None = None
) -> tuple[Array | None, Array | None]:
    """Over (w, dt), from the (rvec, tvec) Jacobian of the corners and their weights: the
    weights' own covariance, and with ``corner_covariance_px2`` the sandwich
    (``sandwich_covariance``; else None). Both None if degenerate."""
    Jw = J * w[:, None]
    info = J.T @ Jw
    # its condition number (symmetric, positive semi-definite: the eigenvalues' ratio)
    eigenvalues = np.linalg.eigvalsh(info)
    if not eigenvalues[0] * 1e14 > eigenvalues[-1]:
        return None, None
    H_inv = np.linalg.inv(info)
    A = np.eye(6)
    A[:3, :3] = _rotation_jacobian(rvec)
    plain = np.asarray(A @ H_inv @ A.T, np.float64)
    if corner_covariance_px2 is None:
        return plain, None
    cov_rt = H_inv @ (Jw.T @ corner_covariance_px2 @ Jw) @ H_inv
    return plain, np.asarray(A @ cov_rt @ A.T, np.float64)


def uncertainty(T: Array, covariance: Array) -> PoseUncertainty:
    """Standard deviations of x, y, z (m) and yaw (rad) for a covariance over (w, dt)."""
    J = measurement_jacobian(T)
    var = np.diag(J @ covariance @ J.T)
    return PoseUncertainty(
        *(math.sqrt(max(float(v), 0.0)) for v in (var[1], var[2], var[3], var[0]))
    )


def measurement_jacobian(T: Array) -> Array:
    """d(yaw, x, y, z) / d(w, dt): (4, 6), to carry a pose covariance to the estimate's
    components."""
    J = np.zeros((4, 6))
    base = yaw_rad(T[:3, :3])
    for k in range(3):
        delta = np.zeros(6)
        delta[k] = _STEP_RAD
        J[0, k] = math.remainder(yaw_rad(_perturbed(T, delta)[:3, :3]) - base, 2 * math.pi)
        J[0, k] /= _STEP_RAD
    J[1:, 3:] = np.eye(3)
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
    sigma = np.repeat(np.broadcast_to(np.asarray(sigma_px, np.float64), (len(detections),)), 4)
    w = _weights(sigma, points.shape[0])
    rvec3, tvec3 = rvec_tvec_from_transform(np.asarray(T_initial, np.float64))
    rvec, tvec = rvec3.reshape(3), tvec3.reshape(3)
    converged: tuple[Array, Array] | None = None
    for _ in range(iterations):
        projected = _project_with_jacobian(camera, rvec, tvec, points)
        if projected is None:
            return None
        r = projected[0] - uv
        J = projected[1]
        Jw = J * w[:, None]
        try:
            delta = -np.linalg.solve(J.T @ Jw + 1e-12 * np.eye(6), Jw.T @ r)
        except np.linalg.LinAlgError:
            return None
        rvec = rvec + delta[:3]
        tvec = tvec + delta[3:]
        if np.max(np.abs(delta)) < CONVERGED:
            # the last step is too small to change the Jacobian: the pixels after it from it
            converged = (projected[0] + J @ delta, J)
            break
    projected = converged or _project_with_jacobian(camera, rvec, tvec, points)
    if projected is None:
        return None
    cov, own = _covariances(projected[1], w, rvec, corner_covariance_px2)
    if cov is None:
        return None
    residual = uv - projected[0]
    rms = float(np.sqrt(np.mean(np.sum(residual.reshape(-1, 2) ** 2, axis=1))))
    T = transform_from_rvec_tvec(rvec, tvec)
    misfit = (
        (math.nan, math.nan)
        if corner_covariance_px2 is None
        else corner_misfit(projected[1], w, residual, corner_covariance_px2)
    )
    return JointPose(T, cov, rms, tuple(d.marker_index for d in detections), own, misfit)


def corner_misfit(J: Array, w: Array, residual: Array, S: Array) -> tuple[float, float]:
    """How well the corners' covariance ``S`` explains the fit's residuals: ``r^T S^-1 r``,
    and its expected value were S right, ``trace(S^-1 M S M^T)`` with ``M = I - J H^-1 J^T W``
    (the residuals of a fit weighted by ``w`` are M times the corners' errors). Their ratio
    is the a-posteriori variance factor: about 1 where S is right, over 1 where the corners
    err more than S says (blur, rolling shutter: errors the edge points' scatter misses).
    (nan, nan) where S is singular."""
    Jw = J * w[:, None]
    M = np.eye(len(residual)) - J @ np.linalg.solve(J.T @ Jw, Jw.T)
    try:
        S_inv = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return math.nan, math.nan
    return float(residual @ S_inv @ residual), float(np.trace(S_inv @ M @ S @ M.T))
