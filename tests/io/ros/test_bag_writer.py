"""A bag written in parts: a run killed outright keeps every part but the last, each a whole
bag that rosbags' own reader opens; a run that ends joins them into one."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("rosbags")

from rosbags.highlevel import AnyReader

from perchpose.io.frames import Stamp, stamp_ns
from perchpose.io.ros.bag_writer import SEGMENT_S, TRACK_TOPIC
from perchpose.values import Estimate

FPS = 5.0
SECONDS = 25.0


def _rows(path: Path) -> list[int]:
    """The frame numbers of the track rows in the bag(s) at ``path`` (a list of them)."""
    paths = path if isinstance(path, list) else [path]
    with AnyReader(paths) as reader:
        connections = [c for c in reader.connections if c.topic == TRACK_TOPIC]
        return [
            json.loads(reader.deserialize(raw, c.msgtype).data)["frame"]
            for c, _, raw in reader.messages(connections=connections)
        ]


def test_a_killed_run_keeps_every_part_but_the_last(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    frames = int(SECONDS * FPS)
    code = f"""
import os
from perchpose.io.frames import Stamp, stamp_ns
from perchpose.io.ros.bag_writer import BagWriter
from perchpose.values import Estimate
writer = BagWriter({str(out)!r})
for k in range({frames}):
    t = k / {FPS}
    writer.write_frame({{"frame": k}}, Estimate.none(t), Stamp(t, stamp_ns(t)))
os._exit(9)  # killed outright: nothing closed, nothing flushed by Python
"""
    result = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True)
    assert result.returncode == 9
    assert not out.exists()
    parts = sorted((tmp_path / "run.mcap.parts").glob("part_*"))
    assert len(parts) == 3  # 0-10 s, 10-20 s, and the part the kill cut
    whole = parts[:-1]
    per_part = int(SEGMENT_S * FPS)
    assert _rows(whole) == list(range(2 * per_part))
    assert all((part / "metadata.yaml").is_file() for part in whole)
    assert not (parts[-1] / "metadata.yaml").exists()


def test_a_run_that_ends_joins_its_parts(tmp_path: Path) -> None:
    from perchpose.io.ros.bag_writer import BagWriter

    out = tmp_path / "run.mcap"
    writer = BagWriter(out)
    frames = int(SECONDS * FPS)
    for k in range(frames):
        t = k / FPS
        writer.write_frame({"frame": k}, Estimate.none(t), Stamp(t, stamp_ns(t)))
    writer.close()
    assert out.is_file()
    assert not (tmp_path / "run.mcap.parts").exists()
    assert not (tmp_path / "run.mcap.bag").exists()
    assert _rows(out) == list(range(frames))
