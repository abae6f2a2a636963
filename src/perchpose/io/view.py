"""A live view in Foxglove (``perchpose track ... --view``; the ``[view]`` extra): a Foxglove
WebSocket server that Foxglove connects to at ``ws://HOST:PORT``, one port behind its Origin gate
(``perchpose.io.view_server``); foxglove-sdk encodes the messages and gives their schemas.

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
from perchpose.io.view_server import FoxgloveServer, ViewChannel
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


OVERLAY, POSE, TF, SCENE, ESTIMATE = range(1, 6)  # the channels' ids


def _channels(m: Any) -> list[ViewChannel]:
    def protobuf(channel_id: int, topic: str, message: Any) -> ViewChannel:
        schema = message.get_schema()
        return ViewChannel(channel_id, topic, schema.encoding, schema.name, bytes(schema.data))

    return [
        protobuf(OVERLAY, "/perchpose/overlay", m.CompressedImage),
        protobuf(POSE, "/perchpose/pose", m.PoseInFrame),
        protobuf(TF, "/tf", m.FrameTransforms),
        protobuf(SCENE, "/perchpose/scene", m.SceneUpdate),
        ViewChannel(
            ESTIMATE,
            "/perchpose/estimate",
            "json",
            "perchpose.Estimate",
            json.dumps(ESTIMATE_SCHEMA).encode(),
        ),
    ]


class LiveView:
    """A Foxglove WebSocket server publishing each frame (``publish``) on ``host:port`` (0: a
    free one, ``self.port`` says which): clients with no Origin, or with one of
    ``allowed_origins`` (the Foxglove web app's by default); ``report`` says each refusal once.
    A message is encoded only while someone subscribes to its channel."""

    def __init__(
        self,
        target: TargetSpec,
        port: int = 8765,
        host: str = "127.0.0.1",
        allowed_origins: tuple[str, ...] = (),
        report: Callable[[str], None] | None = None,
        target_frame: str = TARGET_FRAME,
    ) -> None:
        _foxglove()
        self.target = target
        self.target_frame = target_frame
        self.m = importlib.import_module("foxglove.messages")
        self.server = FoxgloveServer(
            host, port, _channels(self.m), allowed_origins=allowed_origins, report=report
        )
        self.port = self.server.port

    @property
    def wants_overlay(self) -> bool:
        """Whether a client subscribes to the overlay now."""
        return self.server.subscribed(OVERLAY)

    def publish(
        self, stamp: Stamp, estimate: Estimate | None, overlay: NDArray[np.uint8] | None
    ) -> None:
        """One frame: its overlay (drawn by the caller), and its pose, transform and scene
        when valid."""
        m = self.m
        sec, nsec = stamp.sec_nanosec
        t_ns = stamp.t_ns
        time = m.Timestamp(sec=sec, nsec=nsec)
        if overlay is not None and self.server.subscribed(OVERLAY):
            jpeg = encode_jpeg(overlay, 80)
            if jpeg is not None:
                image = m.CompressedImage(
                    timestamp=time, frame_id=stamp.frame_id, data=jpeg, format="jpeg"
                )
                self.server.log(OVERLAY, image.encode(), t_ns)
        valid = estimate is not None and estimate.valid
        row: dict[str, Any] = {"t_s": stamp.t_s, "valid": valid}
        if estimate is not None:
            row |= {
                "predicted": bool(estimate.predicted),
                "age_s": _finite(estimate.age_s),
                "measured": estimate.measured_label,
            }
        if estimate is not None and valid:
            self._pose(estimate, time, stamp.frame_id, t_ns)
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
        self.server.log(ESTIMATE, json.dumps(row).encode(), t_ns)

    def _pose(self, estimate: Estimate, stamp: Any, camera_frame: str, t_ns: int) -> None:
        m = self.m
        T = estimate.T_camera_target
        qx, qy, qz, qw = quaternion_xyzw(T[:3, :3])
        x, y, z = (float(v) for v in T[:3, 3])
        pose = m.Pose(
            position=m.Vector3(x=x, y=y, z=z), orientation=m.Quaternion(x=qx, y=qy, z=qz, w=qw)
        )
        pose_message = m.PoseInFrame(timestamp=stamp, frame_id=camera_frame, pose=pose)
        self.server.log(POSE, pose_message.encode(), t_ns)
        transform = m.FrameTransform(
            timestamp=stamp,
            parent_frame_id=camera_frame,
            child_frame_id=self.target_frame,
            translation=m.Vector3(x=x, y=y, z=z),
            rotation=m.Quaternion(x=qx, y=qy, z=qz, w=qw),
        )
        self.server.log(TF, m.FrameTransforms(transforms=[transform]).encode(), t_ns)
        if not self.server.subscribed(SCENE):
            return
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
        self.server.log(SCENE, m.SceneUpdate(entities=[entity]).encode(), t_ns)

    def close(self) -> None:
        """Stop serving."""
        self.server.close()
