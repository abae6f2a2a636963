"""A track written as ROS 2 messages (the ``[ros]`` extra, through ``rosbags``): ``--out
run.mcap`` makes one MCAP file, which Foxglove and ``ros2 bag`` open; any other name a ROS 2
bag folder with MCAP storage.

Per frame, stamped with the frame's own stamp (a bag's or ROS message's integer nanoseconds,
exactly; else its capture time) in the camera's frame (``--camera-frame``, else the image's
frame id, else ``camera``):
- ``/perchpose/pose``: ``geometry_msgs/PoseWithCovarianceStamped``, the target in the camera
  frame with ``Estimate.covariance`` (ROS's order, x y z then rotation about the frame's axes),
  on frames with a valid pose;
- ``/tf``: ``tf2_msgs/TFMessage``, the camera's frame -> ``target`` (``--target-frame``), on
  the same frames;
- ``/perchpose/overlay/compressed``: ``sensor_msgs/CompressedImage`` (JPEG), the overlay the
  ``--overlay`` video shows, on every frame with an image;
- ``/perchpose/track``: ``std_msgs/String``, the frame's track row as JSON (stage, markers,
  ``predicted``, ``age_s``, ``measured``, timings, errors; numbers as numbers), on every frame.

A bag's index and metadata are written when it is closed, so a run killed outright (a power
loss) would leave nothing readable. The writer therefore writes ``SEGMENT_S`` of frames at a
time into complete bags of their own, ``OUT.parts/part_NNNN`` (each closed, indexed and with
its ``metadata.yaml`` before the next begins), and joins them into ``OUT`` when the run ends:
a killed run leaves every part but the last whole, readable by rosbags or ``ros2 bag`` (all
parts at once: ``AnyReader(sorted(parts))``).
"""

from __future__ import annotations

import importlib
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import PerchposeError
from perchpose.io.frames import TARGET_FRAME, Stamp
from perchpose.io.overlay import encode_jpeg
from perchpose.io.ros.messages import pose_fields
from perchpose.io.sinks import track_json
from perchpose.values import Estimate

POSE_TOPIC = "/perchpose/pose"
TF_TOPIC = "/tf"
OVERLAY_TOPIC = "/perchpose/overlay/compressed"
TRACK_TOPIC = "/perchpose/track"
SEGMENT_S = 10.0  # of frame time per part: what a killed run can lose


def is_bag_output(path: str | Path) -> bool:
    """Whether ``--out`` names a bag: a ``.mcap`` file, or a folder (no file suffix)."""
    return Path(path).suffix.lower() in ("", ".mcap")


def _rosbags(module: str) -> Any:
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise PerchposeError(
            'writing ROS bags needs the ros extra: pip install -e ".[ros]"'
        ) from exc


class BagWriter:
    """Writes a track's frames as ROS 2 messages into ``path`` (``is_bag_output``)."""

    wants_overlay = True

    def __init__(self, path: str | Path, target_frame: str = TARGET_FRAME) -> None:
        self.path = Path(path)
        self.target_frame = target_frame
        rosbag2 = _rosbags("rosbags.rosbag2")
        typesys = _rosbags("rosbags.typesys")
        self.ts = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
        self.types = self.ts.types
        self._rosbag2 = rosbag2
        self._bare = self.path.suffix.lower() == ".mcap"
        self._folder = self.path.with_name(self.path.name + ".bag") if self._bare else self.path
        self.parts = self.path.with_name(self.path.name + ".parts")
        for place in (self.path, self._folder, self.parts):
            if place.exists():
                raise PerchposeError(f"{place}: already exists (a bag is never overwritten)")
        self._part = -1
        self._part_start_s: float | None = None
        self._connections: dict[str, Any] = {}
        try:
            self.parts.mkdir(parents=True)
            self._open_part()
        except OSError as exc:
            raise PerchposeError(f"{self.path}: cannot write ({exc.strerror})") from exc
        self.rows = 0

    def _new_writer(self, folder: Path) -> Any:
        writer = self._rosbag2.Writer(
            folder, version=9, storage_plugin=self._rosbag2.StoragePlugin.MCAP
        )
        writer.open()
        return writer

    def _open_part(self) -> None:
        self._part += 1
        self.writer = self._new_writer(self.parts / f"part_{self._part:04d}")
        self._connections = {}

    def _next_part_if_due(self, t_s: float) -> None:
        """Close the part once it holds ``SEGMENT_S`` of frames, and start the next."""
        if self._part_start_s is None:
            self._part_start_s = t_s
        elif t_s - self._part_start_s >= SEGMENT_S:
            self.writer.close()
            self._open_part()
            self._part_start_s = t_s

    def _write(self, topic: str, msg: Any, t_ns: int) -> None:
        msgtype = msg.__msgtype__
        if topic not in self._connections:
            self._connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
        self.writer.write(self._connections[topic], t_ns, self.ts.serialize_cdr(msg, msgtype))

    def _header(self, stamp: Stamp, frame_id: str) -> Any:
        sec, nanosec = stamp.sec_nanosec
        time = self.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        return self.types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id)

    def write_frame(
        self,
        row: dict[str, Any],
        estimate: Estimate | None,
        stamp: Stamp,
        overlay: NDArray[np.uint8] | None = None,
    ) -> None:
        """One frame: its row, its pose and transform when valid, its overlay (drawn by the
        caller) when it has one; each message stamped with the frame's own stamp."""
        types = self.types
        try:
            self._next_part_if_due(stamp.t_s)
            if estimate is not None and estimate.valid:
                self._pose(estimate, stamp)
            jpeg = None if overlay is None else encode_jpeg(overlay, 90)
            if jpeg is not None:
                msg = types["sensor_msgs/msg/CompressedImage"](
                    header=self._header(stamp, stamp.frame_id),
                    format="jpeg",
                    data=np.frombuffer(jpeg, np.uint8),
                )
                self._write(OVERLAY_TOPIC, msg, stamp.t_ns)
            text = json.dumps(track_json(row))
            self._write(TRACK_TOPIC, types["std_msgs/msg/String"](data=text), stamp.t_ns)
        except OSError as exc:
            raise PerchposeError(f"{self.path}: cannot write ({exc.strerror})") from exc
        self.rows += 1

    def _pose(self, estimate: Estimate, stamp: Stamp) -> None:
        types = self.types
        fields = pose_fields(estimate)
        x, y, z = fields.position
        qx, qy, qz, qw = fields.orientation
        point = types["geometry_msgs/msg/Point"](x=x, y=y, z=z)
        quaternion = types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)
        pose = types["geometry_msgs/msg/PoseWithCovariance"](
            pose=types["geometry_msgs/msg/Pose"](position=point, orientation=quaternion),
            covariance=fields.covariance,
        )
        stamped = types["geometry_msgs/msg/PoseWithCovarianceStamped"](
            header=self._header(stamp, stamp.frame_id), pose=pose
        )
        self._write(POSE_TOPIC, stamped, stamp.t_ns)
        transform = types["geometry_msgs/msg/TransformStamped"](
            header=self._header(stamp, stamp.frame_id),
            child_frame_id=self.target_frame,
            transform=types["geometry_msgs/msg/Transform"](
                translation=types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
                rotation=quaternion,
            ),
        )
        self._write(TF_TOPIC, types["tf2_msgs/msg/TFMessage"](transforms=[transform]), stamp.t_ns)

    def close(self) -> None:
        """Finish the bag: the parts joined into one (for ``.mcap``, its one file moved into
        place), the parts removed."""
        try:
            self.writer.close()
            self._join_parts()
            if self._bare:
                (inner,) = self._folder.glob("*.mcap")
                inner.replace(self.path)
                shutil.rmtree(self._folder)
            shutil.rmtree(self.parts)
        except OSError as exc:
            raise PerchposeError(f"{self.path}: cannot write ({exc.strerror})") from exc

    def _join_parts(self) -> None:
        """Every part's messages, in order, into the bag at ``self._folder``."""
        highlevel = _rosbags("rosbags.highlevel")
        parts = sorted(self.parts.glob("part_*"))
        out = self._new_writer(self._folder)
        connections: dict[tuple[str, str], Any] = {}
        try:
            with highlevel.AnyReader(parts, default_typestore=self.ts) as reader:
                for connection, t_ns, raw in reader.messages():
                    key = (connection.topic, connection.msgtype)
                    if key not in connections:
                        connections[key] = out.add_connection(*key, typestore=self.ts)
                    out.write(connections[key], t_ns, raw)
        finally:
            out.close()
