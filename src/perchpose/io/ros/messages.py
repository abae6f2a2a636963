"""ROS messages as perchpose reads and writes them, whichever library made them (rosbags' types in
bags, rclpy's in the node): an ``Image`` or ``CompressedImage`` as a grey or BGR uint8 array, a
header's stamp as integer nanoseconds, a ``CameraInfo`` as the fields ``CameraModel`` takes,
and an estimate as the fields of a ``PoseWithCovariance``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from perchpose.errors import SourceError
from perchpose.geometry import quaternion_xyzw
from perchpose.io.native import opencv_reason
from perchpose.values import Estimate

ENCODINGS = ("mono8", "mono16", "bgr8", "rgb8", "bgra8", "rgba8")
_CHANNELS = {"mono8": 1, "mono16": 1, "bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4}


def supported(msg: Any) -> bool:
    """A ``CompressedImage``, or an ``Image`` whose encoding perchpose reads."""
    return hasattr(msg, "format") or str(msg.encoding).lower() in ENCODINGS


def _compressed(msg: Any, where: str) -> NDArray[np.uint8]:
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if data.size == 0:
        raise SourceError(f"{where}: the compressed image ({msg.format}) is empty")
    try:
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:  # OpenCV refuses, e.g., a header claiming over 2^30 pixels
        raise SourceError(
            f"{where}: the compressed image ({msg.format}) cannot be decoded ({opencv_reason(exc)})"
        ) from exc
    if image is None or image.size == 0:
        raise SourceError(f"{where}: the compressed image ({msg.format}) cannot be decoded")
    if image.dtype == np.uint16:
        image = (image // 256).astype(np.uint8)
    return np.asarray(image, np.uint8)


def image_of(msg: Any, where: str) -> NDArray[np.uint8]:
    """The grey or BGR uint8 image of an ``Image`` or ``CompressedImage`` message."""
    if hasattr(msg, "format"):
        return _compressed(msg, where)
    encoding = str(msg.encoding).lower()
    if encoding not in ENCODINGS:
        raise SourceError(
            f"{where}: image encoding {msg.encoding!r} is not supported ({', '.join(ENCODINGS)})"
        )
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise SourceError(f"{where}: the image is {w}x{h} pixels: nothing to look at")
    channels = _CHANNELS[encoding]
    depth = 2 if encoding == "mono16" else 1
    raw = np.frombuffer(bytes(msg.data), np.uint8)
    if step < w * channels * depth or raw.size < h * step:
        raise SourceError(f"{where}: the image's data is shorter than {h} rows of {step} bytes")
    rows = raw[: h * step].reshape(h, step)[:, : w * channels * depth]
    if depth == 2:
        dtype = ">u2" if int(msg.is_bigendian) else "<u2"
        grey16 = rows.copy().view(dtype).reshape(h, w)
        return (grey16 // 256).astype(np.uint8)
    image = rows.reshape(h, w, channels) if channels > 1 else rows.reshape(h, w)
    if encoding == "rgb8":
        image = image[:, :, ::-1]
    elif encoding in ("bgra8", "rgba8"):
        image = image[:, :, [2, 1, 0]] if encoding == "rgba8" else image[:, :, :3]
    return np.ascontiguousarray(image, np.uint8)


def header_stamp_ns(header: Any) -> int:
    """A header's stamp as integer nanoseconds (ROS 2's ``sec``/``nanosec``, ROS 1's
    ``secs``/``nsecs``); 0 for an unset stamp."""
    stamp = header.stamp
    seconds = int(getattr(stamp, "sec", getattr(stamp, "secs", 0)))
    nanoseconds = int(getattr(stamp, "nanosec", getattr(stamp, "nsecs", 0)))
    return seconds * 1_000_000_000 + nanoseconds


def camera_info_fields(msg: Any, name: str) -> dict[str, Any]:
    """A ``CameraInfo``'s fields as ``CameraModel.from_camera_info`` takes them (ROS 2 names its
    matrices ``k`` and ``d``; ROS 1, ``K`` and ``D``)."""
    return {
        "k": [float(v) for v in getattr(msg, "k", getattr(msg, "K", []))],
        "d": [float(v) for v in getattr(msg, "d", getattr(msg, "D", []))],
        "distortion_model": str(msg.distortion_model) or "plumb_bob",
        "width": int(msg.width),
        "height": int(msg.height),
        "camera_name": name,
    }


@dataclass(frozen=True)
class PoseFields:
    """An estimate as a ``geometry_msgs/PoseWithCovariance`` holds it: ``position`` (x, y, z)
    in metres, ``orientation`` (x, y, z, w), ``covariance`` the 36 values row by row over x, y,
    z and rotation about the frame's x, y, z axes (``Estimate.covariance``; all zero, ROS's
    "not given", where it is not finite)."""

    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    covariance: NDArray[np.float64]


def pose_fields(estimate: Estimate) -> PoseFields:
    """The fields of ``estimate``'s pose of the target in the camera frame."""
    T = estimate.T_camera_target
    x, y, z = (float(v) for v in T[:3, 3])
    covariance = np.asarray(estimate.covariance, np.float64)
    if not np.all(np.isfinite(covariance)):
        covariance = np.zeros((6, 6))
    return PoseFields((x, y, z), quaternion_xyzw(T[:3, :3]), covariance.reshape(-1).copy())
