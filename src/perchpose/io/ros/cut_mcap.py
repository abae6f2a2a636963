"""A bare MCAP file cut short, read as far as it goes (the ``mcap`` library, in the ``ros``
extra).

A recorder killed outright leaves an MCAP without its summary and footer, and rosbags (which
reads the summary first) cannot open it. ``CutMcap`` reads the records in order with the
``mcap`` library's stream reader, as far as they are whole, and offers the small part of
rosbags' reader interface that ``perchpose.io.ros.rosbag`` uses (``connections``, ``messages``,
``deserialize``), deserializing with rosbags' ROS 2 type store. ``damage`` says where the file
stops making sense.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader


class McapConnection(NamedTuple):
    """A channel of the file, named as rosbags names its connections."""

    id: int
    topic: str
    msgtype: str
    msgcount: int


class CutMcap:
    """The whole records of ``path``, in order."""

    def __init__(self, path: Path) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        self.typestore = get_typestore(Stores.ROS2_HUMBLE)
        self.damage = "it ends cleanly"
        counts: Counter[int] = Counter()
        channels: dict[int, tuple[str, int]] = {}
        schemas: dict[int, str] = {}
        for record in self._records():
            if isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                channels[record.id] = (record.topic, record.schema_id)
            elif isinstance(record, Message):
                counts[record.channel_id] += 1
        self.connections = [
            McapConnection(cid, topic, schemas.get(schema_id, ""), counts[cid])
            for cid, (topic, schema_id) in channels.items()
        ]

    def _records(self) -> Iterator[Any]:
        """Every whole record; where the file is cut, ``damage`` says so and the records end."""
        with self.path.open("rb") as stream:
            try:
                yield from StreamReader(stream).records
            except Exception as exc:  # a cut record, a cut chunk: the mcap library's errors
                why = str(exc).strip() or type(exc).__name__
                self.damage = f"its records stop at byte {stream.tell()}: {why}"

    def messages(
        self, connections: list[McapConnection] | None = None
    ) -> Iterator[tuple[McapConnection, int, bytes]]:
        wanted = {c.id: c for c in connections or self.connections}
        for record in self._records():
            if isinstance(record, Message) and record.channel_id in wanted:
                yield wanted[record.channel_id], record.log_time, record.data

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        return self.typestore.deserialize_cdr(raw, msgtype)

    def open(self) -> None:
        """Nothing to open (read on each pass)."""

    def close(self) -> None:
        """Nothing to close (each pass closes its file)."""
