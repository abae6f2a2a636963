"""The target as MAVLink's LANDING_TARGET message describes it, from an ``Estimate``.

Frames:
- body FLU: the body frame of ``T_body_camera`` (x forward, y left, z up), as in
  ``perchpose.control``.
- body FRD: x forward, y right, z down, MAVLink's ``MAV_FRAME_BODY_FRD`` (what ArduPilot takes);
  ``p_frd = diag(1, -1, -1) @ p_flu``.
- local NED: the body FRD vector rotated by the vehicle's attitude ``R_ned_frd`` (roll, pitch,
  yaw from MAVLink's ATTITUDE) and, when the vehicle's position in its local frame is known,
  shifted by it, so x, y, z are the target's position in the vehicle's local frame (what PX4
  takes for ``MAV_FRAME_LOCAL_NED``).

``angle_x``/``angle_y`` are the target centre's angular offsets from the optical axis along the
image's x and y axes, ``size_x``/``size_y`` the angle the largest marker spans, ``q`` the
rotation about the frame's z axis that turns the frame's x axis onto the target's x axis.
"""

from __future__ import annotations

import math
from dataclasses import astuple, dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import LinkError
from perchpose.values import Estimate

Array = NDArray[np.float64]

FRAMES = ("body_frd", "local_ned")
R_FRD_FLU = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class LandingTarget:
    """LANDING_TARGET's fields, SI units (metres, radians, microseconds)."""

    time_usec: int
    frame: str
    x_m: float
    y_m: float
    z_m: float
    distance_m: float
    angle_x_rad: float
    angle_y_rad: float
    size_x_rad: float
    size_y_rad: float
    q_wxyz: tuple[float, float, float, float]


# ArduCopter's precision landing takes a target only along its descent: a line of sight this
# close to the body's down axis (here: the camera's optical axis within 60 degrees of it)
MIN_DOWN_COSINE = 0.5


def check_line_of_sight(T_body_camera: Array, frame: str) -> None:
    """Refuse a mounting whose LANDING_TARGET an autopilot would drop without a word:
    ``body_frd`` is ArduPilot's frame, and ArduCopter uses a target only when its line of
    sight points down along the descent (its approach vector is fixed body-down), so a camera
    that does not look down gets a ``LinkError`` that says what to use instead."""
    if frame != "body_frd":
        return
    axis_frd = R_FRD_FLU @ np.asarray(T_body_camera, np.float64)[:3, 2]
    if float(axis_frd[2]) >= MIN_DOWN_COSINE:
        return
    looks = "up" if float(axis_frd[2]) <= -MIN_DOWN_COSINE else "sideways"
    raise LinkError(
        f"LANDING_TARGET in body_frd (ArduPilot) from a camera looking {looks}: ArduCopter "
        "drops every target whose line of sight does not point down along its descent; to "
        "land, mount the camera looking down (--mount down); to perch on a target above, "
        "fly with the perching controller (--crazyflie)"
    )


def R_ned_frd_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Array:
    """The vehicle's attitude as MAVLink's ATTITUDE gives it (Z-Y-X Euler angles) as a matrix
    mapping body FRD vectors into local NED."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def target_in_body_m(estimate: Estimate, T_body_camera: Array) -> Array:
    """(3,) the target centre in the body frame (FLU), metres."""
    T = np.asarray(T_body_camera, np.float64)
    return T[:3, :3] @ estimate.t_m + T[:3, 3]


def landing_target(
    estimate: Estimate,
    T_body_camera: Array,
    target_side_m: float,
    *,
    frame: str = "body_frd",
    R_ned_frd: Array | None = None,
    p_ned_vehicle_m: Array | None = None,
    time_usec: int | None = None,
) -> LandingTarget:
    """LANDING_TARGET for a valid estimate; ``frame`` is ``body_frd`` or ``local_ned`` (which
    needs ``R_ned_frd``; ``p_ned_vehicle_m`` makes the position absolute). ``time_usec``: the
    capture time on the autopilot's clock (default: the estimate's ``t_s``)."""
    if frame not in FRAMES:
        raise LinkError(f"unknown LANDING_TARGET frame {frame!r} (choose {', '.join(FRAMES)})")
    if not estimate.valid:
        raise LinkError(f"frame at t = {estimate.t_s:.3f} s has no valid estimate to send")
    p_camera_m = estimate.t_m
    R_body_camera = T_body_camera[:3, :3]
    p_frd_m = R_FRD_FLU @ target_in_body_m(estimate, T_body_camera)
    yaw = estimate.yaw_rad
    x_target_frd = R_FRD_FLU @ R_body_camera @ np.array([math.cos(yaw), math.sin(yaw), 0.0])
    if frame == "local_ned":
        if R_ned_frd is None:
            raise LinkError("local_ned needs the vehicle's attitude (no ATTITUDE message yet)")
        p_m = R_ned_frd @ p_frd_m
        if p_ned_vehicle_m is not None:
            p_m = p_m + np.asarray(p_ned_vehicle_m, dtype=float)
        x_target = R_ned_frd @ x_target_frd
    else:
        p_m = p_frd_m
        x_target = x_target_frd
    heading = math.atan2(float(x_target[1]), float(x_target[0]))
    distance = float(np.linalg.norm(p_camera_m))
    depth = max(float(p_camera_m[2]), 1e-9)
    size = 2.0 * math.atan(0.5 * target_side_m / max(distance, 1e-9))
    message = LandingTarget(
        time_usec=round(estimate.t_s * 1e6) if time_usec is None else time_usec,
        frame=frame,
        x_m=float(p_m[0]),
        y_m=float(p_m[1]),
        z_m=float(p_m[2]),
        distance_m=distance,
        angle_x_rad=math.atan2(float(p_camera_m[0]), depth),
        angle_y_rad=math.atan2(float(p_camera_m[1]), depth),
        size_x_rad=size,
        size_y_rad=size,
        q_wxyz=(math.cos(heading / 2.0), 0.0, 0.0, math.sin(heading / 2.0)),
    )
    numbers = [v for v in astuple(message) if isinstance(v, float)] + list(message.q_wxyz)
    if not all(math.isfinite(v) for v in numbers):
        raise LinkError(
            f"frame at t = {estimate.t_s:.3f} s: LANDING_TARGET would carry a non-finite field "
            "(estimate, attitude or vehicle position); not sent"
        )
    return message


@dataclass(frozen=True)
class DistanceReading:
    """DISTANCE_SENSOR's fields: the distance to the target's plane along the body's vertical
    axis (cm), its variance (cm^2, 255: unknown) and which way it looks
    (``MAV_SENSOR_ROTATION_PITCH_270``: down, ``PITCH_90``: up)."""

    current_cm: int
    covariance_cm2: int
    orientation: int


MAV_SENSOR_ROTATION_PITCH_90 = 24  # looking up
MAV_SENSOR_ROTATION_PITCH_270 = 25  # looking down


def distance_reading(
    estimate: Estimate, T_body_camera: Array, max_cm: int
) -> DistanceReading | None:
    """The marker's range as a rangefinder along the body's vertical axis would give it, for a
    camera looking up or down (within 60 degrees); None for one looking sideways, a target on
    the wrong side, or a range outside (0, max_cm]."""
    axis_flu = np.asarray(T_body_camera, np.float64)[:3, 2]
    if abs(float(axis_flu[2])) < MIN_DOWN_COSINE:
        return None
    up = float(axis_flu[2]) > 0
    p_flu = target_in_body_m(estimate, T_body_camera)
    along_m = float(p_flu[2]) if up else -float(p_flu[2])
    current_cm = round(along_m * 100.0)
    if not math.isfinite(along_m) or not 0 < current_cm <= max_cm:
        return None
    variance = float(estimate.covariance[2, 2]) * 1e4  # the optical axis is near the body's
    covariance = min(254, max(0, round(variance))) if math.isfinite(variance) else 255
    orientation = MAV_SENSOR_ROTATION_PITCH_90 if up else MAV_SENSOR_ROTATION_PITCH_270
    return DistanceReading(current_cm, covariance, orientation)
