"""MCAP files cut short, read as far as they go (the ``mcap`` library, in the ``ros`` extra).

A recorder killed outright leaves an MCAP without its summary and footer, and rosbags (which
reads the summary first) cannot open it; ``ros2 bag record`` killed so also leaves its bag folder
without ``metadata.yaml``, which rosbags needs too. ``CutMcap`` reads the records of one file, or
of a bag folder's files in order, with the ``mcap`` library's stream reader, as far as they are
whole, and offers the small part of rosbags' reader interface that ``perchpose.io.ros.rosbag``
uses (``connections``, ``messages``, ``deserialize``), deserializing with rosbags' ROS 2 type
store. ``damage`` says where the first file that stops making sense stops.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

from perchpose.io.ros.salvaged import SalvagedBag


class CutMcap(SalvagedBag):
    """The whole records of ``paths`` (one file, or a bag folder's files in order)."""

    def __init__(self, paths: Sequence[Path]) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.paths = list(paths)
        super().__init__(get_typestore(Stores.ROS2_HUMBLE))

    def _records(self, path: Path) -> Iterator[Any]:
        """Every whole record of ``path``; where it is cut, ``damage`` says so (for the first
        such file) and its records end."""
        with path.open("rb") as stream:
            try:
                yield from StreamReader(stream).records
            except Exception as exc:  # a cut record, a cut chunk: the mcap library's errors
                why = str(exc).strip() or type(exc).__name__
                where = f"{path.name}: " if len(self.paths) > 1 else ""
                self._damaged(f"{where}its records stop at byte {stream.tell()}: {why}")

    def _messages(self) -> Iterator[tuple[int, int, bytes]]:
        """(connection id, log time, data) of every whole message, file after file; a topic
        and type seen first makes a new connection."""
        for path in self.paths:
            schemas: dict[int, str] = {}
            channels: dict[int, int] = {}  # this file's channel id -> connection id
            for record in self._records(path):
                if isinstance(record, Schema):
                    schemas[record.id] = record.name
                elif isinstance(record, Channel):
                    key = (record.topic, schemas.get(record.schema_id, ""))
                    channels[record.id] = self._connection_id(*key)
                elif isinstance(record, Message) and record.channel_id in channels:
                    yield channels[record.channel_id], record.log_time, record.data
