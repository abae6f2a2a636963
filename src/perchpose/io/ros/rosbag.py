"""Frames from ROS bags through ``rosbags`` (the ``[ros]`` extra): ROS 1 ``.bag`` files, ROS 2
bag folders (sqlite3 or MCAP storage) and bare ``.mcap`` files, with their images as
``sensor_msgs/Image`` (mono8, mono16, bgr8, rgb8, bgra8, rgba8) or ``CompressedImage``, and the
camera from a ``CameraInfo`` topic.

One ``Frame`` per image message, in the bag's order; ``t_s`` from the message's header stamp
(the bag's receive time where the stamp is zero); ``file`` is ``BAG#TOPIC#N``. One damaged
message (bytes that do not deserialize, a cut JPEG, image data shorter than its rows, a stamp
that goes backwards) is a flagged frame without an image, as a damaged video's frame is, and
the reading goes on; an image encoding perchpose does not read, or a bag that cannot be read
on, ends the reading with a ``SourceError`` after the frames before it."""

from __future__ import annotations

import importlib
import logging
import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from perchpose.camera import CameraModel
from perchpose.errors import SourceError
from perchpose.io.frames import IMAGE_SUFFIXES, Frame, FrameSource, natural_key
from perchpose.io.ros.messages import camera_info_fields, header_stamp_ns, image_of, supported

log = logging.getLogger(__name__)

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
BAG_SUFFIXES = (".bag", ".mcap")


def is_bag(source: str) -> bool:
    """A ROS 1 ``.bag``, a bare ``.mcap`` or a ROS 2 bag folder: one with ``metadata.yaml``,
    or (a recorder that never closed it) with ``.mcap`` or ``.db3`` files and no images."""
    path = Path(source)
    if path.suffix.lower() in BAG_SUFFIXES:
        return True
    if not path.is_dir():
        return False
    return (path / "metadata.yaml").is_file() or (
        bool(_storage_files(path, ".mcap") or _storage_files(path, ".db3"))
        and not any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir())
    )


def _storage_files(folder: Path, suffix: str) -> list[Path]:
    """A bag folder's ``suffix`` files in the order they were written (``run_0``, ``run_1``,
    ..., ``run_10``)."""
    return sorted((p for p in folder.glob(f"*{suffix}") if p.is_file()), key=natural_key)


def _rosbags() -> Any:
    try:
        return importlib.import_module("rosbags.highlevel")
    except ImportError as exc:
        raise SourceError('reading ROS bags needs the ros extra: pip install -e ".[ros]"') from exc


def _open(path: Path) -> Any:
    if not path.exists():
        raise SourceError(f"{path}: no such file or folder")
    highlevel = _rosbags()
    try:
        reader = highlevel.AnyReader([path])
        reader.open()
    except Exception as exc:  # rosbags raises its own error kinds per format
        salvaged = _salvage(path)
        if salvaged is None:
            raise SourceError(f"{path}: not a readable ROS bag ({_first_line(exc)})") from exc
        return salvaged
    return reader


def _salvage(path: Path) -> Any:
    """A ROS 1 bag, a bare ``.mcap``, or a ROS 2 bag folder of MCAP or sqlite3 files, that
    rosbags cannot open (cut short before its index or summary, or its folder left without
    ``metadata.yaml``: a recorder killed outright), read in order up to the damage
    (``CutRos1``, ``CutMcap``, ``UnclosedSqlite``); None for anything else."""
    reader = _salvaged_reader(path)
    if reader is None or not reader.connections:
        return None
    unclosed = path.is_dir() and not (path / "metadata.yaml").is_file()
    why = "no metadata.yaml, " * unclosed + reader.damage
    log.warning("%s: cut short (%s); reading its messages in order up to the damage", path, why)
    return reader


def _salvaged_reader(path: Path) -> Any:
    """The reader of what a killed recorder left at ``path`` (None: nothing it could read)."""
    if path.is_file() and path.suffix.lower() == ".bag":
        from perchpose.io.ros.cut_ros1 import CutRos1

        return CutRos1(path)
    if path.is_file() and path.suffix.lower() == ".mcap":
        mcaps, db3s = [path], []
    elif path.is_dir():
        mcaps, db3s = _storage_files(path, ".mcap"), _storage_files(path, ".db3")
    else:
        return None
    if db3s and not mcaps:
        from perchpose.io.ros.unclosed_sqlite import UnclosedSqlite

        return UnclosedSqlite(db3s)
    if not mcaps:
        return None
    try:
        from perchpose.io.ros.cut_mcap import CutMcap
    except ImportError:  # the mcap library is not installed
        return None
    return CutMcap(mcaps)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _topics_of(reader: Any, kinds: tuple[str, ...]) -> list[str]:
    return sorted({c.topic for c in reader.connections if c.msgtype in kinds})


def _connection(reader: Any, path: Path, topic: str, kinds: tuple[str, ...], what: str) -> Any:
    found = [c for c in reader.connections if c.topic == topic]
    if not found:
        available = ", ".join(_topics_of(reader, kinds)) or "none"
        raise SourceError(f"{path}: no topic {topic!r} in the bag ({what} topics: {available})")
    if found[0].msgtype not in kinds:
        raise SourceError(
            f"{path}: topic {topic!r} holds {found[0].msgtype}, not {' or '.join(kinds)}"
        )
    return found[0]


def _stamp_ns(msg: Any, bag_time_ns: int) -> int:
    """The message's header stamp, or the bag's receive time where the stamp is zero."""
    return header_stamp_ns(msg.header) or bag_time_ns


class BagSource(FrameSource):
    """The images of one topic of a bag, as ``Frame`` in the bag's order."""

    def __init__(self, path: str | Path, image_topic: str) -> None:
        self.path = Path(path)
        reader = _open(self.path)
        try:
            self.connection = _connection(reader, self.path, image_topic, IMAGE_TYPES, "image")
        finally:
            reader.close()
        self.topic = image_topic
        count = int(self.connection.msgcount)
        super().__init__(f"{self.path} {image_topic}", count, 30.0)

    def __iter__(self) -> Iterator[Frame]:
        reader = _open(self.path)
        try:
            connections = [c for c in reader.connections if c.topic == self.topic]
            messages = reader.messages(connections=connections)
            index = 0
            last_t_s = -math.inf
            while True:
                where = f"{self.path} {self.topic} message {index}"
                try:
                    item = next(messages, None)
                except Exception as exc:  # a damaged bag: each format fails its own way
                    raise SourceError(f"{where}: cannot be read ({_first_line(exc)})") from exc
                if item is None:
                    return
                frame = self._frame(reader, item, index, where, last_t_s)
                if frame.image is not None:
                    last_t_s = frame.t_s
                yield frame
                index += 1
        finally:
            reader.close()

    def _frame(
        self, reader: Any, item: tuple[Any, int, bytes], index: int, where: str, last_t_s: float
    ) -> Frame:
        """The message's frame, or a flagged one without an image where it is damaged."""
        connection, bag_time_ns, raw = item
        name, file = f"message {index}", f"{self.path}#{self.topic}#{index}"
        fallback_t_s = last_t_s if math.isfinite(last_t_s) else bag_time_ns * 1e-9
        try:
            msg = reader.deserialize(raw, connection.msgtype)
        except Exception as exc:  # bytes that are not the message they claim to be
            why = f"{where}: cannot be deserialized ({_first_line(exc)}); skipped"
            return Frame(index, fallback_t_s, None, name, why, file)
        t_ns = _stamp_ns(msg, bag_time_ns)
        t_s = t_ns / 1_000_000_000
        if t_s < last_t_s:
            why = (
                f"{where}: its stamp goes back {1000 * (last_t_s - t_s):.1f} ms from the frame "
                "before; skipped"
            )
            return Frame(index, last_t_s, None, name, why, file)
        try:
            image = image_of(msg, where)
        except SourceError as exc:
            if not supported(msg):
                raise  # the topic's encoding, not this message: no frame of it can be read
            return Frame(index, t_s, None, name, f"{exc}; skipped", file)  # cut data
        frame_id = str(getattr(msg.header, "frame_id", ""))
        return Frame(
            index,
            t_s,
            image,
            name,
            file=file,
            grabbed_s=time.monotonic(),
            stamp_ns=t_ns,
            frame_id=frame_id,
        )


def camera_from_bag(path: str | Path, topic: str | None = None) -> CameraModel:
    """The camera of the first ``CameraInfo`` message on ``topic`` (default: the bag's only
    CameraInfo topic)."""
    where = Path(path)
    reader = _open(where)
    try:
        topics = _topics_of(reader, (CAMERA_INFO_TYPE,))
        if topic is None:
            if len(topics) != 1:
                found = ", ".join(topics) if topics else "none"
                raise SourceError(
                    f"{where}: give --camera, or --camera-info-topic to pick the CameraInfo "
                    f"topic (found: {found})"
                )
            topic = topics[0]
        connection = _connection(reader, where, topic, (CAMERA_INFO_TYPE,), "CameraInfo")
        for conn, _, raw in reader.messages(connections=[connection]):
            msg = reader.deserialize(raw, conn.msgtype)
            data = camera_info_fields(msg, topic)
            return CameraModel.from_camera_info(data, f"{where} {topic}")
        raise SourceError(f"{where}: topic {topic!r} holds no message")
    finally:
        reader.close()
