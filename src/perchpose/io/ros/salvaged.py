"""The part of rosbags' reader interface that ``perchpose.io.ros.rosbag`` uses
(``connections``, ``messages``, ``deserialize``), for the readers of what a killed recorder
leaves (``cut_ros1``, ``cut_mcap``, ``unclosed_sqlite``): each gives its messages in order,
as far as they can be read, and says in ``damage`` where that stops."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from typing import Any, NamedTuple

CLEAN = "it ends cleanly"


class Topic(NamedTuple):
    """A topic of the bag (one per topic and type), named as rosbags names its connections."""

    id: int
    topic: str
    msgtype: str
    msgcount: int


class SalvagedBag:
    """A reader of messages read in order. A subclass sets what ``_messages`` reads, then
    calls ``__init__``, which counts each topic's messages in one pass; ``_connection_id``
    numbers a topic and type the first time ``_messages`` meets it."""

    def __init__(self, typestore: Any) -> None:
        self.typestore = typestore
        self.damage = CLEAN
        self._ids: dict[tuple[str, str], int] = {}
        counts: Counter[int] = Counter()
        for connection_id, _, _ in self._counted():
            counts[connection_id] += 1
        self.connections = [
            Topic(cid, topic, msgtype, counts[cid]) for (topic, msgtype), cid in self._ids.items()
        ]

    def _messages(self) -> Iterator[tuple[int, int, bytes]]:
        """(connection id, time in ns, serialized data) of every message that can be read."""
        raise NotImplementedError

    def _counted(self) -> Iterator[tuple[int, int, bytes]]:
        """The pass that counts the messages (``_messages``, or a cheaper one without data)."""
        return self._messages()

    def _connection_id(self, topic: str, msgtype: str) -> int:
        return self._ids.setdefault((topic, msgtype), len(self._ids))

    def _damaged(self, why: str) -> None:
        """Say where the messages stop (the first place only)."""
        if self.damage == CLEAN:
            self.damage = why

    def messages(
        self, connections: list[Topic] | None = None
    ) -> Iterator[tuple[Topic, int, bytes]]:
        wanted = {c.id: c for c in connections or self.connections}
        for connection_id, t_ns, raw in self._messages():
            if connection_id in wanted:
                yield wanted[connection_id], t_ns, raw

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        return self.typestore.deserialize_cdr(raw, msgtype)

    def open(self) -> None:
        """Nothing to open (read on each pass)."""

    def close(self) -> None:
        """Nothing to close (each pass closes its files)."""
