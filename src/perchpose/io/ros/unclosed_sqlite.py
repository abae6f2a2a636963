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
from collections.abc import Iterator, Sequence
from contextlib import closing
from pathlib import Path

from perchpose.io.ros.salvaged import SalvagedBag


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


class UnclosedSqlite(SalvagedBag):
    """The readable messages of ``paths`` (a bag folder's ``.db3`` files in order)."""

    def __init__(self, paths: Sequence[Path]) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.paths = list(paths)
        super().__init__(get_typestore(Stores.ROS2_HUMBLE))

    def _counted(self) -> Iterator[tuple[int, int, bytes]]:
        return self._messages(with_data=False)

    def _messages(self, with_data: bool = True) -> Iterator[tuple[int, int, bytes]]:
        """(connection id, time, data) of every readable message, file after file, in the
        order they were written; a topic and type seen first makes a new connection."""
        data = "data" if with_data else "NULL"
        for path in self.paths:
            try:
                with closing(_connect(path)) as db:
                    topics = {
                        topic_id: self._connection_id(name, msgtype)
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
                self._damaged(f"{path.name}: its messages stop there: {exc}")
