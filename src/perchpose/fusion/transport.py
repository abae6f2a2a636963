"""A pose's covariance carried between parametrisations: from the joint fit's (w, dt) to
[roll, pitch, yaw, x, y, z] (``angles_covariance``), and from there to the estimate's [x, y, z]
and a small rotation vector about the camera's axes (``camera_covariance``)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from perchpose.geometry import (
    rotation_vector_jacobian,
    rotation_vector_jacobian_inverse,
    tilt_rad,
    yaw_rad,
)
from perchpose.numeric.linalg import sandwiched

Array = NDArray[np.float64]


def angles_covariance(T: Array, covariance_w_dt: Array) -> Array:
    """A pose covariance over (w, dt) (``pose.joint``) carried to (6, 6) over
    [roll, pitch, yaw, x, y, z] (``geometry.tilt_rad``, ``geometry.yaw_rad``)."""
    _, pitch = tilt_rad(T[:3, :3])
    A = np.eye(6)
    A[:3, :3] = rotation_vector_jacobian_inverse(yaw_rad(T[:3, :3]), pitch)
    return sandwiched(A, np.asarray(covariance_w_dt, np.float64))


def camera_covariance(yaw_rad_: float, pitch_rad: float, covariance_angles: Array) -> Array:
    """A covariance over [roll, pitch, yaw, x, y, z] carried to the estimate's (6, 6) over
    [x, y, z] and a small rotation vector about the camera's axes."""
    B = np.zeros((6, 6))
    B[0, 3] = B[1, 4] = B[2, 5] = 1.0
    B[3:, :3] = rotation_vector_jacobian(yaw_rad_, pitch_rad)
    out = sandwiched(B, np.asarray(covariance_angles, np.float64))
    return np.asarray(0.5 * (out + out.T), np.float64)
