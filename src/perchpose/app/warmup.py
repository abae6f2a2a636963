"""``perchpose warmup``: every compiled kernel built and cached on disk, ahead of a flight."""

from __future__ import annotations

from dataclasses import dataclass

from perchpose.app.inputs import load_camera, load_target
from perchpose.warmup import Warmup, warm_up


@dataclass(frozen=True)
class WarmupOptions:
    """The camera (a calibration file or ``preset:NAME``; None: the presets' lenses only) and
    the target file (None: the paper's) the flight will use."""

    camera_file: str | None = None
    target_file: str | None = None


def run(options: WarmupOptions) -> Warmup:
    """Build (or load from the disk cache) every kernel the camera and target run."""
    cameras = [] if options.camera_file is None else [load_camera(options.camera_file)]
    return warm_up(load_target(options.target_file), cameras)
