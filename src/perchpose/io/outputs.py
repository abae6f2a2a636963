"""Where ``perchpose track --out`` writes, chosen by the name: a pose file or a ROS 2 bag."""

from __future__ import annotations

from pathlib import Path

from perchpose.io.frames import TARGET_FRAME
from perchpose.io.sinks import PoseWriter, TrackWriter
from perchpose.target import TargetSpec


def open_track_writer(
    out: str | Path, target: TargetSpec, target_frame: str = TARGET_FRAME
) -> TrackWriter:
    """A ``.csv`` or ``.jsonl`` pose file, or a ROS 2 bag for ``.mcap`` or a folder name (its
    transforms to ``target_frame``)."""
    from perchpose.io.ros.bag_writer import BagWriter, is_bag_output

    if is_bag_output(out):
        return BagWriter(out, target_frame)
    return PoseWriter(out, target)
