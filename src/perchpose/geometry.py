"""Rigid transforms, yaw and angle wrapping.

Naming rule, used everywhere in perchpose: ``T_a_b`` is a 4x4 homogeneous transform that maps
points from frame b into frame a, ``p_a = T_a_b @ p_b``, so that ``T_a_c = T_a_b @ T_b_c``.
``R_a_b`` is its 3x3 rotation and ``t_a_b_m`` its translation in metres.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def wrap_angle_rad(angle_rad: float) -> float:
    """Wrap an angle to (-pi, pi]."""
    wrapped = math.remainder(angle_rad, 2.0 * math.pi)
    return math.pi if wrapped == -math.pi else wrapped


def wrap_angle_deg(angle_deg: float) -> float:
    """Wrap an angle to (-180, 180]."""
    return math.degrees(wrap_angle_rad(math.radians(angle_deg)))


def angle_diff_rad(a_rad: float, b_rad: float) -> float:
    """The signed difference ``a - b`` on the circle, in (-pi, pi]."""
    return wrap_angle_rad(a_rad - b_rad)


def weighted_circular_mean_rad(angles_rad: Array, weights: Array) -> float:
    """Weighted mean of angles on the circle.

    angles_rad : (N,) float, radians.
    weights : (N,) float, non-negative, not all zero.
    """
    s = float(np.sum(weights * np.sin(angles_rad)))
    c = float(np.sum(weights * np.cos(angles_rad)))
    return wrap_angle_rad(math.atan2(s, c))


def check_transform(T: object, name: str = "T") -> Array:
    """Return ``T`` as a (4, 4) float64 rigid transform or raise ValueError naming ``name``."""
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 transform, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has non-finite entries")
    R = arr[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError(f"{name} rotation is not orthonormal with determinant +1")
    if not np.allclose(arr[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"{name} last row must be [0, 0, 0, 1]")
    return arr


def make_transform(R: Array, t_m: Array) -> Array:
    """Build a 4x4 transform from a (3, 3) rotation and a (3,) translation in metres."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t_m, dtype=np.float64).reshape(3)
    return T


def invert_transform(T_a_b: Array) -> Array:
    """Return ``T_b_a`` for a rigid ``T_a_b``."""
    R = T_a_b[:3, :3]
    t = T_a_b[:3, 3]
    return make_transform(R.T, -R.T @ t)


def transform_from_rvec_tvec(rvec: Array, tvec_m: Array) -> Array:
    """Build ``T_camera_object`` from OpenCV's Rodrigues vector and translation (metres)."""
    import cv2  # here, not above: the controller and the vehicle links import this module

    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return make_transform(np.asarray(R, dtype=np.float64), np.asarray(tvec_m).reshape(3))


def rvec_tvec_from_transform(T: Array) -> tuple[Array, Array]:
    """Return OpenCV's (Rodrigues vector (3, 1), translation (3, 1)) for a 4x4 transform."""
    import cv2  # here, not above: the controller and the vehicle links import this module

    rvec, _ = cv2.Rodrigues(np.ascontiguousarray(T[:3, :3]))
    return np.asarray(rvec, dtype=np.float64).reshape(3, 1), T[:3, 3].reshape(3, 1).copy()


def yaw_rad(R_camera_target: Array) -> float:
    """The target's yaw in the camera frame: ``atan2(R[1,0], R[0,0])`` in (-pi, pi]."""
    return wrap_angle_rad(math.atan2(float(R_camera_target[1, 0]), float(R_camera_target[0, 0])))


def rot_x(angle_rad: float) -> Array:
    """Rotation about x by ``angle_rad``."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> Array:
    """Rotation about y by ``angle_rad``."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> Array:
    """Rotation about z by ``angle_rad``."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# A target facing the camera, upright in the image: target x = camera x, target y = -camera y
# (up in the image), target z = -camera z (its printed face looks back at the camera).
R_CAMERA_TARGET_FACING = np.diag([1.0, -1.0, -1.0])


def facing_pose(
    x_m: float,
    y_m: float,
    z_m: float,
    yaw_rad_: float = 0.0,
    tilt_x_rad: float = 0.0,
    tilt_y_rad: float = 0.0,
) -> Array:
    """``T_camera_target`` of a target facing the camera at (x, y, z) metres in the camera frame.

    ``yaw_rad_`` turns the target about the optical axis (it is then the estimate's yaw);
    ``tilt_x_rad`` and ``tilt_y_rad`` tilt the target plane about the camera's x and y axes.
    """
    R = rot_x(tilt_x_rad) @ rot_y(tilt_y_rad) @ rot_z(yaw_rad_) @ R_CAMERA_TARGET_FACING
    return make_transform(R, np.array([x_m, y_m, z_m]))


def rotation_from_vector(w_rad: Array) -> Array:
    """``exp([w]x)`` (3, 3) of the rotation vector ``w`` (Rodrigues' formula, numpy only: the
    controller imports no OpenCV)."""
    w = np.asarray(w_rad, np.float64).reshape(3)
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    k = w / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    R: Array = np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)
    return R


def vector_from_rotation(R: Array) -> Array:
    """The rotation vector (3,) of a rotation ``R`` turned by less than pi (the inverse of
    ``rotation_from_vector``)."""
    R = np.asarray(R, np.float64)
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin_angle = 0.5 * float(np.linalg.norm(axis))
    cos_angle = 0.5 * (float(np.trace(R)) - 1.0)
    angle = math.atan2(sin_angle, cos_angle)
    if sin_angle < 1e-12:
        return 0.5 * axis  # no turn (to first order)
    w: Array = axis * (angle / (2.0 * sin_angle))
    return w


def roll_pitch_rad(R: Array) -> tuple[float, float]:
    """(roll, pitch) of ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (z-y-x angles, as a vehicle's
    attitude is given), radians; ``yaw_rad`` is the third."""
    pitch = -math.asin(max(-1.0, min(1.0, float(R[2, 0]))))
    roll = math.atan2(float(R[2, 1]), float(R[2, 2]))
    return roll, pitch


def clip_norm(v: Array, limit: float) -> Array:
    """``v`` scaled down to length ``limit`` where it is longer."""
    size = float(np.linalg.norm(v))
    if size > limit:
        scaled: Array = v * (limit / size)
        return scaled
    return v


def leaned(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, float]:
    """The horizontal acceleration per unit of vertical (world x and y: the tangent of the
    thrust's tilt) of a body at this roll and pitch (``roll_pitch_rad``'s angles) under
    heading ``yaw_rad``."""
    forward = math.tan(pitch_rad)
    left = -math.tan(roll_rad) / math.cos(pitch_rad)
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return c * forward - s * left, s * forward + c * left


def lean_deg(R_world_body: Array) -> float:
    """The angle between the body's z axis and the world's vertical, degrees."""
    return math.degrees(math.acos(float(np.clip(R_world_body[2, 2], -1.0, 1.0))))


def tilt_rad(R_camera_target: Array) -> tuple[float, float]:
    """(roll, pitch) of the target's plane, radians, with the estimate's yaw (``yaw_rad``)
    completing them: ``R = Rz(yaw) Ry(pitch) Rx(roll) R_CAMERA_TARGET_FACING``. Both are 0
    for a target facing the camera (``facing_pose`` without tilt), whatever its yaw."""
    return roll_pitch_rad(np.asarray(R_camera_target, np.float64) @ R_CAMERA_TARGET_FACING)


def rotation_from_angles(yaw_rad_: float, roll_rad: float, pitch_rad: float) -> Array:
    """``R_camera_target`` of a yaw (``yaw_rad``) and a tilt (``tilt_rad``)."""
    R: Array = rot_z(yaw_rad_) @ rot_y(pitch_rad) @ rot_x(roll_rad) @ R_CAMERA_TARGET_FACING
    return R


def rotation_vector_jacobian(yaw_rad_: float, pitch_rad: float) -> Array:
    """d w / d(roll, pitch, yaw) (3, 3): how the angles of ``rotation_from_angles`` move the
    rotation, as a small rotation vector ``w`` about the camera's axes (``R' = exp([w]) R``).
    Its columns: the roll axis ``Rz Ry x``, the pitch axis ``Rz y``, the yaw axis ``z``."""
    c, s = math.cos(yaw_rad_), math.sin(yaw_rad_)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    return np.array([[c * cp, -s, 0.0], [s * cp, c, 0.0], [-sp, 0.0, 1.0]])


def rotation_vector_jacobian_inverse(yaw_rad_: float, pitch_rad: float) -> Array:
    """d(roll, pitch, yaw) / d w (3, 3): the inverse of ``rotation_vector_jacobian``, written
    out (its determinant is cos(pitch): none at pitch +/-90 deg, where roll and yaw are one
    turn)."""
    c, s = math.cos(yaw_rad_), math.sin(yaw_rad_)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    return np.array([[c / cp, s / cp, 0.0], [-s, c, 0.0], [sp * c / cp, sp * s / cp, 1.0]])


def rotation_from_quaternion(qw: float, qx: float, qy: float, qz: float) -> Array:
    """The rotation matrix of a quaternion (normalised first; all zero: the identity)."""
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz) or 1.0
    w, x, y, z = qw / n, qx / n, qy / n, qz / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quaternion_xyzw(R: Array) -> tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w) of a rotation matrix, w >= 0."""
    m = np.asarray(R, np.float64)
    w = math.sqrt(max(0.0, 1.0 + m[0, 0] + m[1, 1] + m[2, 2])) / 2.0
    x = math.copysign(
        math.sqrt(max(0.0, 1.0 + m[0, 0] - m[1, 1] - m[2, 2])) / 2.0, m[2, 1] - m[1, 2]
    )
    y = math.copysign(
        math.sqrt(max(0.0, 1.0 - m[0, 0] + m[1, 1] - m[2, 2])) / 2.0, m[0, 2] - m[2, 0]
    )
    z = math.copysign(
        math.sqrt(max(0.0, 1.0 - m[0, 0] - m[1, 1] + m[2, 2])) / 2.0, m[1, 0] - m[0, 1]
    )
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    return x / norm, y / norm, z / norm, w / norm
