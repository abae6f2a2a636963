"""A live view in Foxglove (``perchpose track ... --view``; the ``[view]`` extra): a Foxglove
WebSocket server (``foxglove-sdk``) that Foxglove connects to at ``ws://HOST:PORT``.

Channels, per frame, stamped with the frame's own stamp (``io.frames.Stamp``: a bag's or ROS
message's integer nanoseconds, exactly; else its capture time), in the camera's frame
(``--camera-frame``, else the image's frame id, else ``camera``):
- ``/perchpose/overlay``: ``foxglove.CompressedImage`` (JPEG), the overlay the ``--overlay``
  video shows;
- ``/perchpose/pose``: ``foxglove.PoseInFrame``, the target in the camera's frame (valid
  frames);
- ``/tf``: ``foxglove.FrameTransforms``, the camera's frame -> the target's (``--target-frame``,
  default ``target``; valid frames);
- ``/perchpose/scene``: ``foxglove.SceneUpdate``, the target's plate (the printed sheet) and
  its largest marker in the target's frame, for the 3D panel (valid frames);
- ``/perchpose/estimate``: JSON ``{t_s, valid, stage, x_cm, y_cm, z_cm, yaw_deg, roll_deg,
  pitch_deg, latency_ms, predicted, age_s, measured}`` for the Plot panel (every frame):
  ``predicted`` whether the pose is the filter's prediction with no marker measured in this
  frame, ``age_s`` the age of the newest measurement behind it, ``measured`` the markers
  measured (``m0+m1``).
"""

from __future__ import annotations

import importlib
import json
import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import PerchposeError
from perchpose.geometry import quaternion_xyzw
from perchpose.io.frames import TARGET_FRAME, Stamp
from perchpose.io.overlay import encode_jpeg
from perchpose.io.view_gate import OriginGate
from perchpose.target import TargetSpec
from perchpose.values import Estimate

ESTIMATE_SCHEMA = {
    "type": "object",
    "properties": {
        name: {"type": "number"}
        for name in (
            "t_s",
            "stage",
            "x_cm",
            "y_cm",
            "z_cm",
            "yaw_deg",
            "roll_deg",
            "pitch_deg",
            "latency_ms",
            "age_s",
        )
    }
    | {
        "valid": {"type": "boolean"},
        "predicted": {"type": "boolean"},
        "measured": {"type": "string"},
    },
}


def _foxglove() -> Any:
    try:
        return importlib.import_module("foxglove")
    except ImportError as exc:
        raise PerchposeError(
            'the live view needs the view extra: pip install -e ".[view]"'
        ) from exc


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


class LiveView:
    """A Foxglove WebSocket server publishing each frame (``publish``); ``port`` 0 picks a free
    one (``self.port`` says which). Clients reach it through an ``OriginGate``
    (``perchpose.io.view_gate``): no Origin, or ``allowed_origins`` (the Foxglove web app's by
    default); ``report`` says each refusal once."""

    def __init__(
        self,
        target: TargetSpec,
        port: int = 8765,
        host: str = "127.0.0.1",
        allowed_origins: tuple[str, ...] = (),
        report: Callable[[str], None] | None = None,
        target_frame: str = TARGET_FRAME,
    ) -> None:
        fox = _foxglove()
        self.target = target
        self.target_frame = target_frame
        self.m = importlib.import_module("foxglove.messages")
        channels = importlib.import_module("foxglove.channels")
        try:  # on loopback only: every client comes through the gate
            self.server = fox.start_server(name="perchpose", host="127.0.0.1", port=0)
        except Exception as exc:  # the SDK reports its own error kinds
            raise PerchposeError(f"--view: cannot start the Foxglove server ({exc})") from exc
        try:
            self.gate = OriginGate(host, port, int(self.server.port), allowed_origins, report)
        except PerchposeError:
            self.server.stop()
            raise
        self.port = self.gate.port
        self.image = channels.CompressedImageChannel("/perchpose/overlay")
        self.pose = channels.PoseInFrameChannel("/perchpose/pose")
        self.tf = channels.FrameTransformsChannel("/tf")
        self.scene = channels.SceneUpdateChannel("/perchpose/scene")
        self.estimate = fox.Channel(
            "/perchpose/estimate", schema=ESTIMATE_SCHEMA, message_encoding="json"
        )

    def publish(
        self, stamp: Stamp, estimate: Estimate | None, overlay: NDArray[np.uint8] | None
    ) -> None:
        """One frame: its overlay (drawn by the caller), and its pose, transform and scene
        when valid."""
        m = self.m
        sec, nsec = stamp.sec_nanosec
        time = m.Timestamp(sec=sec, nsec=nsec)
        jpeg = None if overlay is None else encode_jpeg(overlay, 80)
        if jpeg is not None:
            self.image.log(
                m.CompressedImage(timestamp=time, frame_id=stamp.frame_id, data=jpeg, format="jpeg")
            )
        valid = estimate is not None and estimate.valid
        row: dict[str, Any] = {"t_s": stamp.t_s, "valid": valid}
        if estimate is not None:
            row |= {
                "predicted": bool(estimate.predicted),
                "age_s": _finite(estimate.age_s),
                "measured": estimate.measured_label,
            }
        if estimate is not None and valid:
            self._pose(estimate, time, stamp.frame_id)
            row |= {
                "stage": estimate.stage,
                "x_cm": _finite(estimate.x_cm),
                "y_cm": _finite(estimate.y_cm),
                "z_cm": _finite(estimate.z_cm),
                "yaw_deg": _finite(estimate.yaw_deg),
                "roll_deg": _finite(math.degrees(estimate.roll_rad)),
                "pitch_deg": _finite(math.degrees(estimate.pitch_rad)),
                "latency_ms": _finite(estimate.latency_s * 1e3),
            }
        self.estimate.log(json.dumps(row).encode())

    def _pose(self, estimate: Estimate, stamp: Any, camera_frame: str) -> None:
        m = self.m
        T = estimate.T_camera_target
        qx, qy, qz, qw = quaternion_xyzw(T[:3, :3])
        x, y, z = (float(v) for v in T[:3, 3])
        pose = m.Pose(
            position=m.Vector3(x=x, y=y, z=z), orientation=m.Quaternion(x=qx, y=qy, z=qz, w=qw)
        )
        self.pose.log(m.PoseInFrame(timestamp=stamp, frame_id=camera_frame, pose=pose))
        transform = m.FrameTransform(
            timestamp=stamp,
            parent_frame_id=camera_frame,
            child_frame_id=self.target_frame,
            translation=m.Vector3(x=x, y=y, z=z),
            rotation=m.Quaternion(x=qx, y=qy, z=qz, w=qw),
        )
        self.tf.log(m.FrameTransforms(transforms=[transform]))
        sheet = 2.0 * self.target.sheet_half_extent_m
        side = self.target.markers[0].side_m
        centre = m.Pose(
            position=m.Vector3(x=0.0, y=0.0, z=0.0),
            orientation=m.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
        )
        cubes = [
            m.CubePrimitive(
                pose=centre,
                size=m.Vector3(x=sheet, y=sheet, z=0.002),
                color=m.Color(r=0.9, g=0.9, b=0.9, a=0.8),
            ),
            m.CubePrimitive(
                pose=centre,
                size=m.Vector3(x=side, y=side, z=0.003),
                color=m.Color(r=0.1, g=0.1, b=0.1, a=0.9),
            ),
        ]
        entity = m.SceneEntity(
            timestamp=stamp, frame_id=self.target_frame, id="target", cubes=cubes
        )
        self.scene.log(m.SceneUpdate(entities=[entity]))

    def close(self) -> None:
        """Stop serving."""
        self.gate.close()
        self.server.stop()
