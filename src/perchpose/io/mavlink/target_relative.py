"""MAVLink's TARGET_RELATIVE (id 511), which PX4's vision target estimator takes: the target's
position with its standard deviations, from an ``Estimate`` and its covariance.

pymavlink 2.4.50's shipped dialects do not define the message yet, so
``perchpose_targets.xml`` (beside this module, in ``dialects/``) holds it as MAVLink's
development dialect publishes it (same field names, types and order, so the same CRC extra,
28), and pymavlink's own generator (``mavgen``) turns it into a Python module on first use,
in memory (``dialect``). Its message class is packed by the link's own ``MAVLink`` object, so the
sequence numbers and the system and component ids are the link's.

Frames (``TARGET_OBS_FRAME``): ``body_frd`` sends ``BODY_FRD`` (1), with ``q_sensor`` the
vehicle's attitude (FRD to NED) once ATTITUDE has arrived (all zero before: ignored);
``local_ned`` sends ``LOCAL_OFFSET_NED`` (2): the body vector rotated by the attitude, origin
on the vehicle. The position covariance (camera frame) is rotated into the frame; ``yaw_std``
is the rotation covariance's variance about the frame's z axis.
"""

from __future__ import annotations

import contextlib
import functools
import io
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import LinkError
from perchpose.geometry import quaternion_xyzw
from perchpose.io.mavlink.landing_target import R_FRD_FLU, target_in_body_m
from perchpose.values import Estimate

Array = NDArray[np.float64]

DIALECT_XML = Path(__file__).parent / "dialects" / "perchpose_targets.xml"
OBS_FRAMES = {"body_frd": 1, "local_ned": 2}  # TARGET_OBS_FRAME_BODY_FRD, _LOCAL_OFFSET_NED
LANDING_TARGET_TYPE_VISION_FIDUCIAL = 2


@dataclass(frozen=True)
class TargetRelative:
    """TARGET_RELATIVE's fields (metres, radians, microseconds; quaternions w, x, y, z)."""

    timestamp_usec: int
    frame: str
    x_m: float
    y_m: float
    z_m: float
    pos_std_m: tuple[float, float, float]
    yaw_std_rad: float
    q_target_wxyz: tuple[float, float, float, float]
    q_sensor_wxyz: tuple[float, float, float, float]


def _wxyz(R: Array) -> tuple[float, float, float, float]:
    x, y, z, w = quaternion_xyzw(R)
    return (w, x, y, z)


def target_relative(
    estimate: Estimate,
    T_body_camera: Array,
    *,
    frame: str = "body_frd",
    R_ned_frd: Array | None = None,
    timestamp_usec: int | None = None,
) -> TargetRelative:
    """TARGET_RELATIVE for a valid estimate with a covariance (``LinkError`` otherwise);
    ``local_ned`` needs ``R_ned_frd``. ``timestamp_usec``: the capture time on the autopilot's
    clock (default: the estimate's ``t_s``)."""
    if frame not in OBS_FRAMES:
        raise LinkError(f"unknown TARGET_RELATIVE frame {frame!r} (choose body_frd, local_ned)")
    if not estimate.valid:
        raise LinkError(f"frame at t = {estimate.t_s:.3f} s has no valid estimate to send")
    C = estimate.covariance
    if not np.all(np.isfinite(C)):
        raise LinkError(
            f"frame at t = {estimate.t_s:.3f} s: no covariance for TARGET_RELATIVE's standard "
            "deviations; not sent"
        )
    R_frd_camera = R_FRD_FLU @ T_body_camera[:3, :3]
    p_frd_m = R_FRD_FLU @ target_in_body_m(estimate, T_body_camera)
    q_sensor = (0.0, 0.0, 0.0, 0.0)
    if frame == "local_ned":
        if R_ned_frd is None:
            raise LinkError("local_ned needs the vehicle's attitude (no ATTITUDE message yet)")
        R_frame_camera = R_ned_frd @ R_frd_camera
        p_m = R_ned_frd @ p_frd_m
    else:
        R_frame_camera = R_frd_camera
        p_m = p_frd_m
        if R_ned_frd is not None:
            q_sensor = _wxyz(R_ned_frd)
    position = R_frame_camera @ C[:3, :3] @ R_frame_camera.T
    rotation = R_frame_camera @ C[3:, 3:] @ R_frame_camera.T
    pos_std = tuple(math.sqrt(max(0.0, float(v))) for v in np.diag(position))
    message = TargetRelative(
        timestamp_usec=round(estimate.t_s * 1e6) if timestamp_usec is None else timestamp_usec,
        frame=frame,
        x_m=float(p_m[0]),
        y_m=float(p_m[1]),
        z_m=float(p_m[2]),
        pos_std_m=(pos_std[0], pos_std[1], pos_std[2]),
        yaw_std_rad=math.sqrt(max(0.0, float(rotation[2, 2]))),
        q_target_wxyz=_wxyz(R_frame_camera @ estimate.T_camera_target[:3, :3]),
        q_sensor_wxyz=q_sensor,
    )
    numbers = [message.x_m, message.y_m, message.z_m, *message.pos_std_m, message.yaw_std_rad]
    numbers += [*message.q_target_wxyz, *message.q_sensor_wxyz]
    if not all(math.isfinite(v) for v in numbers):
        raise LinkError(
            f"frame at t = {estimate.t_s:.3f} s: TARGET_RELATIVE would carry a non-finite "
            "field (estimate or attitude); not sent"
        )
    return message


@functools.cache
def dialect() -> ModuleType:
    """The Python module pymavlink's generator makes of ``perchpose_targets.xml``, once per
    process: generated into a fresh private folder (``tempfile``'s: this user's alone, mode
    0700), read into memory, the folder removed, and the code run from memory. Nothing is
    imported from a place another local user could have written (a predictable cache folder
    under the shared temporary directory would let them plant code that runs as us)."""
    try:
        from pymavlink.generator import mavgen
    except ImportError as exc:
        raise LinkError("MAVLink needs pymavlink: pip install 'perchpose[mavlink]'") from exc
    with tempfile.TemporaryDirectory(prefix="perchpose-mavlink-") as private:
        options = mavgen.Opts(
            str(Path(private) / "perchpose_targets"),
            wire_protocol="2.0",
            language="Python3",
            validate=False,
        )
        with contextlib.redirect_stdout(io.StringIO()):  # mavgen narrates each step
            ok = mavgen.mavgen(options, [str(DIALECT_XML)])
        generated = Path(private) / "perchpose_targets.py"
        if not ok or not generated.exists():
            raise LinkError(f"pymavlink's generator failed on {DIALECT_XML}")
        source = generated.read_text(encoding="utf-8")
    module = ModuleType("perchpose_targets", f"generated by pymavlink from {DIALECT_XML.name}")
    exec(compile(source, f"<pymavlink dialect {DIALECT_XML.name}>", "exec"), module.__dict__)
    return module


def target_relative_send(mav: Any, *, msg: TargetRelative) -> None:
    """Send ``msg`` through a pymavlink ``MAVLink`` object (``conn.mav``)."""
    message = dialect().MAVLink_target_relative_message(
        msg.timestamp_usec,
        0,
        OBS_FRAMES[msg.frame],
        msg.x_m,
        msg.y_m,
        msg.z_m,
        list(msg.pos_std_m),
        msg.yaw_std_rad,
        list(msg.q_target_wxyz),
        list(msg.q_sensor_wxyz),
        LANDING_TARGET_TYPE_VISION_FIDUCIAL,
    )
    mav.send(message)
