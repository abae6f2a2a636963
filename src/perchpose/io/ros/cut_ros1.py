"""ROS 1 bags cut short, read as far as they go (the bag format 2.0 read record by record;
rosbags deserializes).

``rosbag record`` writes its index (connection records, chunk infos) at the end of the file and
its position into the bag header when it closes: killed outright, it leaves the header pointing
nowhere, and rosbags, which reads the index first, cannot open the bag (``rosbag reindex`` is
the ROS tool for it). The chunks before the cut still hold every message and its connection.
``CutRos1`` reads them in order (chunks stored plain, bz2 or lz4), as far as their records are
whole, and offers the small part of rosbags' reader interface that ``perchpose.io.ros.rosbag``
uses (``connections``, ``messages``, ``deserialize``). ``damage`` says where the file stops.

The format: "#ROSBAG V2.0\\n", then records, each a little-endian uint32 header length, the
header (fields, each a uint32 length then ``name=value``), a uint32 data length and the data.
The header's ``op`` says the kind: 0x02 message data (``conn``, ``time``), 0x03 bag header,
0x04 index data, 0x05 chunk (``compression``, ``size``; its data are records), 0x06 chunk
info, 0x07 connection (``conn``, ``topic``; its data are fields: ``type``, ``md5sum``, ...).
"""

from __future__ import annotations

import bz2
import mmap
import struct
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path
from typing import Any

from perchpose.io.ros.salvaged import SalvagedBag

Buffer = bytes | mmap.mmap

MAGIC = b"#ROSBAG V2.0\n"
OP_MESSAGE, OP_CHUNK, OP_CONNECTION = 0x02, 0x05, 0x07


class CutRecordError(Exception):
    """A record that the file or its chunk ends inside."""


def _fields(data: bytes) -> dict[str, bytes]:
    """The ``name=value`` fields of a record header (or a connection's data)."""
    fields: dict[str, bytes] = {}
    at = 0
    while at < len(data):
        if at + 4 > len(data):
            raise CutRecordError("a header field is cut")
        (size,) = struct.unpack_from("<I", data, at)
        field = data[at + 4 : at + 4 + size]
        if len(field) < size or b"=" not in field:
            raise CutRecordError("a header field is cut")
        name, value = field.split(b"=", 1)
        fields[name.decode("ascii", "replace")] = value
        at += 4 + size
    return fields


def _records(data: Buffer, start: int) -> Iterator[tuple[dict[str, bytes], bytes, bool]]:
    """(header fields, data, whole) of each record of ``data`` from ``start``: the last one
    comes with as much of its data as there is, ``whole`` False, where the data is cut;
    ``CutRecordError`` where a header is."""
    at = start
    while at < len(data):
        if at + 4 > len(data):
            raise CutRecordError(f"a record's length is cut at byte {at}")
        (header_size,) = struct.unpack_from("<I", data, at)
        header_end = at + 4 + header_size
        if header_end + 4 > len(data):
            raise CutRecordError(f"a record's header is cut at byte {at}")
        (data_size,) = struct.unpack_from("<I", data, header_end)
        body = bytes(data[header_end + 4 : header_end + 4 + data_size])
        whole = len(body) == data_size
        yield _fields(bytes(data[at + 4 : header_end])), body, whole
        if not whole:
            raise CutRecordError(f"a record's data is cut at byte {at}")
        at = header_end + 4 + data_size


def _unpacked(header: dict[str, bytes], body: bytes) -> bytes:
    """A chunk's records, decompressed."""
    compression = header.get("compression", b"none").decode("ascii", "replace")
    if compression == "none":
        return body
    if compression == "bz2":
        return bz2.decompress(body)
    if compression == "lz4":
        import lz4.frame  # rosbags' own dependency

        unpacked: bytes = lz4.frame.decompress(body)
        return unpacked
    raise CutRecordError(f"a chunk compressed as {compression!r}")


class CutRos1(SalvagedBag):
    """The whole message records of the ROS 1 bag ``path``, in order."""

    def __init__(self, path: Path) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        super().__init__(get_typestore(Stores.ROS1_NOETIC))

    def _messages(self) -> Iterator[tuple[int, int, bytes]]:
        """(connection id, time in ns, data) of every whole message, in the file's order (a
        plain chunk cut short gives the messages it still holds whole)."""
        if self.path.stat().st_size < len(MAGIC):
            self._damaged("not a ROS 1 bag (format 2.0)")
            return
        with (
            self.path.open("rb") as f,
            closing(mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)) as data,
        ):
            if data[: len(MAGIC)] != MAGIC:
                self._damaged("not a ROS 1 bag (format 2.0)")
                return
            connections: dict[int, int] = {}  # the bag's conn -> connection id
            try:
                for header, body, whole in _records(data, len(MAGIC)):
                    if header.get("op") != bytes([OP_CHUNK]):
                        continue
                    plain = header.get("compression", b"none") == b"none"
                    if not whole and not plain:
                        continue  # a compressed chunk cut short: nothing in it can be read
                    try:
                        unpacked = _unpacked(header, body)
                    except (OSError, ValueError, RuntimeError) as exc:  # bz2, lz4
                        raise CutRecordError(f"a chunk does not decompress ({exc})") from exc
                    yield from self._chunk(unpacked, connections)
            except CutRecordError as exc:
                self._damaged(str(exc))

    def _chunk(self, data: bytes, connections: dict[int, int]) -> Iterator[tuple[int, int, bytes]]:
        """The messages of one chunk, as far as they are whole."""
        for header, body, whole in _records(data, 0):
            if not whole:
                return
            op = header.get("op", b"")
            if op == bytes([OP_CONNECTION]) and "conn" in header:
                described = _fields(body)
                topic = header.get("topic", described.get("topic", b"")).decode()
                msgtype = _ros2_name(described.get("type", b"").decode())
                (conn,) = struct.unpack("<I", header["conn"])
                connections[conn] = self._connection_id(topic, msgtype)
            elif op == bytes([OP_MESSAGE]) and "conn" in header and "time" in header:
                (conn,) = struct.unpack("<I", header["conn"])
                sec, nsec = struct.unpack("<II", header["time"])
                if conn in connections:
                    yield connections[conn], sec * 1_000_000_000 + nsec, body

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        return self.typestore.deserialize_ros1(raw, msgtype)


def _ros2_name(ros1_type: str) -> str:
    """``sensor_msgs/Image`` as rosbags names it: ``sensor_msgs/msg/Image``."""
    package, _, name = ros1_type.partition("/")
    return f"{package}/msg/{name}" if name and "/msg/" not in ros1_type else ros1_type
