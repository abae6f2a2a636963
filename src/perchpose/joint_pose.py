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
from perchpose.detection import MarkerDetection
from perchpose.geometry import rvec_tvec_from_transform, transform_from_rvec_tvec, yaw_rad
from perchpose.target import TargetSpec

Array = NDArray[np.float64]
_STEP_RAD = 1e-6
_STEP_M = 1e-6


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
    it was computed with; reproj_rms_px over all corners; markers used."""

    T_camera_target: Array
    covariance: Array
    reproj_rms_px: float
    markers: tuple[int, ...]

    @property
    def std(self) -> PoseUncertainty:
        return uncertainty(self.T_camera_target, self.covariance)


def _perturbed(T: Array, delta: Array) -> Array:
    rot, _ = cv2.Rodrigues(np.asarray(delta[:3], np.float64).reshape(3, 1))
    out = T.copy()
    out[:3, :3] = np.asarray(rot, np.float64) @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + delta[3:]
    return out


def _project(camera: CameraModel, T: Array, points_target_m: Array) -> Array | None:
    uv, ok = camera.project((T[:3, :3] @ points_target_m.T).T + T[:3, 3])
    return np.asarray(uv, np.float64).reshape(-1) if bool(np.all(ok)) else None


def corner_jacobian(camera: CameraModel, T: Array, points_target_m: Array) -> Array | None:
    """d(pixel coordinates) / d(delta): (2N, 6), by central differences; None if a point
    leaves the lens model's field."""
    columns = []
    for k in range(6):
        step = _STEP_RAD if k < 3 else _STEP_M
        delta = np.zeros(6)
        delta[k] = step
        plus = _project(camera, _perturbed(T, delta), points_target_m)
        minus = _project(camera, _perturbed(T, -delta), points_target_m)
        if plus is None or minus is None:
            return None
        columns.append((plus - minus) / (2.0 * step))
    return np.stack(columns, axis=1)


def pose_covariance(
    camera: CameraModel, T: Array, points_target_m: Array, sigma_px: float | Array
) -> Array | None:
    """``(J^T W J)^-1`` with ``W = 1 / sigma^2`` at ``T`` for corners ``points_target_m``
    (N, 3) with pixel noise ``sigma_px`` per axis (one value, or one per corner): the pose's
    covariance, and at the true pose the Cramer-Rao bound. None if degenerate."""
    J = corner_jacobian(camera, T, points_target_m)
    if J is None:
        return None
    sigma = np.broadcast_to(np.asarray(sigma_px, np.float64), (points_target_m.shape[0],))
    w = np.repeat(1.0 / sigma**2, 2)
    info = J.T @ (J * w[:, None])
    if np.linalg.cond(info) > 1e14:
        return None
    return np.asarray(np.linalg.inv(info), np.float64)


def uncertainty(T: Array, covariance: Array) -> PoseUncertainty:
    """Standard deviations of x, y, z (m) and yaw (rad) for a covariance over (w, dt)."""
    grad = np.zeros(6)
    base = yaw_rad(T[:3, :3])
    for k in range(3):
        delta = np.zeros(6)
        delta[k] = _STEP_RAD
        d = yaw_rad(_perturbed(T, delta)[:3, :3]) - base
        grad[k] = math.remainder(d, 2.0 * math.pi) / _STEP_RAD
    var = np.diag(covariance)
    return PoseUncertainty(
        math.sqrt(max(float(var[3]), 0.0)),
        math.sqrt(max(float(var[4]), 0.0)),
        math.sqrt(max(float(var[5]), 0.0)),
        math.sqrt(max(float(grad @ covariance @ grad), 0.0)),
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
    iterations: int = 8,
) -> JointPose | None:
    """Least-squares pose from every corner of ``detections`` (pixel residuals through the
    lens model weighted by ``1 / sigma_px^2``, one value or one per detection; Gauss-Newton
    from ``T_initial``, e.g. the best single-marker pose)."""
    if not detections:
        return None
    points = target_points(target, detections)
    uv = np.concatenate([d.corners_px for d in detections]).reshape(-1)
    sigma = np.repeat(np.broadcast_to(np.asarray(sigma_px, np.float64), (len(detections),)), 4)
    w = np.repeat(1.0 / sigma**2, 2)
    T = np.asarray(T_initial, np.float64).copy()
    for _ in range(iterations):
        projected = _project(camera, T, points)
        J = corner_jacobian(camera, T, points)
        if projected is None or J is None:
            return None
        r = projected - uv
        Jw = J * w[:, None]
        try:
            delta = -np.linalg.solve(J.T @ Jw + 1e-12 * np.eye(6), Jw.T @ r)
        except np.linalg.LinAlgError:
            return None
        T = _perturbed(T, delta)
        if np.max(np.abs(delta[:3])) < 1e-9 and np.max(np.abs(delta[3:])) < 1e-9:
            break
    # keep the rotation exactly orthonormal after the updates
    rvec, tvec = rvec_tvec_from_transform(T)
    T = transform_from_rvec_tvec(rvec, tvec)
    projected = _project(camera, T, points)
    cov = pose_covariance(camera, T, points, sigma)
    if projected is None or cov is None:
        return None
    rms = float(np.sqrt(np.mean(np.sum((projected - uv).reshape(-1, 2) ** 2, axis=1))))
    return JointPose(T, cov, rms, tuple(d.marker_index for d in detections))
