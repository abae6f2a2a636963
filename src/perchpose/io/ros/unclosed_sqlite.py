"""ROS 2 sqlite3 bags that their recorder never closed, read as far as they go (Python's own
``sqlite3``; rosbags deserializes).

``ros2 bag record`` writes ``metadata.yaml`` when it closes: killed outright, it leaves its
``.db3`` files without it, and rosbags cannot open the folder. Each file's ``topics`` and
``messages`` tables are all a track needs. ``UnclosedSqlite`` reads them file after file, in the
order the messages were written, up to a page that cannot be read (a file cut short), and offers
the small part of rosbags' reader interface that ``perchpose.io.ros.rosbag`` uses
(``connections``, ``messages``, ``deserialize``). ``damage`` says where the first file that
stops making sense stops.
"""

from __future__ import annotations

import sqlite3
from collections import Counter
from collections.abc import Iterator, Sequence
from contextlib import closing
from pathlib import Path
from typing import Any, NamedTuple


class SqliteConnection(NamedTuple):
    """A topic of the files (one per topic and type), named as rosbags names its connections."""

    id: int
    topic: str
    msgtype: str
    msgcount: int


def _connect(path: Path) -> sqlite3.Connection:
    """``path`` opened read-only; where a journal left by the killed recorder stops that, the
    file as it is on the disk (``immutable``: the journal's pages are not applied)."""
    connection = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
    try:
        connection.execute("SELECT count(*) FROM sqlite_master").fetchone()
    except sqlite3.Error:
        connection.close()
        connection = sqlite3.connect(f"{path.resolve().as_uri()}?immutable=1", uri=True)
    return connection


class UnclosedSqlite:
    """The readable messages of ``paths`` (a bag folder's ``.db3`` files in order)."""

    def __init__(self, paths: Sequence[Path]) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.paths = list(paths)
        self.typestore = get_typestore(Stores.ROS2_HUMBLE)
        self.damage = "it ends cleanly"
        self._ids: dict[tuple[str, str], int] = {}
        counts: Counter[int] = Counter()
        for connection_id, _, _ in self._messages(with_data=False):
            counts[connection_id] += 1
        self.connections = [
            SqliteConnection(cid, topic, msgtype, counts[cid])
            for (topic, msgtype), cid in self._ids.items()
        ]

    def _messages(self, with_data: bool = True) -> Iterator[tuple[int, int, bytes]]:
        """(connection id, time, data) of every readable message, file after file, in the
        order they were written; a topic and type seen first makes a new connection."""
        data = "data" if with_data else "NULL"
        for path in self.paths:
            try:
                with closing(_connect(path)) as db:
                    topics = {
                        topic_id: self._ids.setdefault((name, msgtype), len(self._ids))
                        for topic_id, name, msgtype in db.execute(
                            "SELECT id, name, type FROM topics"
                        )
                    }
                    rows = db.execute(
                        f"SELECT topic_id, timestamp, {data} FROM messages ORDER BY id"
                    )
                    for topic_id, t_ns, raw in rows:
                        if topic_id in topics:
                            yield topics[topic_id], int(t_ns), bytes(raw or b"")
            except sqlite3.Error as exc:  # a page cut off, a file that is not a database
                if self.damage == "it ends cleanly":
                    self.damage = f"{path.name}: its messages stop there: {exc}"

    def messages(
        self, connections: list[SqliteConnection] | None = None
    ) -> Iterator[tuple[SqliteConnection, int, bytes]]:
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
