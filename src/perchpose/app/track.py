"""Tracking a frame source into a pose file (the ``perchpose track`` command)."""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from perchpose.camera import CameraModel
from perchpose.errors import ImageError, PerchposeError
from perchpose.estimator import PerchingEstimator
from perchpose.io.overlay import OverlayWriter, check_overlay_path, draw_overlay
from perchpose.io.sinks import PoseWriter, estimate_row
from perchpose.io.sources import open_source
from perchpose.target import TargetSpec
from perchpose.values import Estimate


@dataclass(frozen=True)
class TrackSummary:
    """What a tracking run did."""

    frames: int
    valid: int
    bad_frames: int
    stage_counts: dict[int, int]
    mean_ms: float
    out: Path


def track(
    source: str,
    camera: CameraModel,
    target: TargetSpec,
    out: str | Path,
    *,
    fps: float | None = None,
    overlay: str | Path | None = None,
    progress: bool = True,
    warn: Callable[[str], None] | None = None,
    on_frame: Sequence[Callable[[Estimate | None, float], None]] = (),
    estimator: PerchingEstimator | None = None,
) -> TrackSummary:
    """Run the estimator over every frame of ``source`` and write one row per frame to ``out``.

    A frame that cannot be read or has the wrong size gets an invalid row and a warning; the run
    goes on. The first frame having a size other than the calibration's is an error, since then
    every frame would be. Each of ``on_frame`` (vehicle links) is called once per frame with the
    estimate (None for an unreadable frame) and the frame's time.
    """
    if overlay is not None:
        check_overlay_path(overlay)
    frames = open_source(source, fps)
    est = estimator or PerchingEstimator(camera, target)
    say = warn or (lambda msg: print(f"warning: {msg}", file=sys.stderr))
    writer = PoseWriter(out, target)
    video: OverlayWriter | None = None
    n = valid = bad = 0
    stage_counts = {0: 0, 1: 0, 2: 0, 3: 0}
    total_ms = 0.0
    first_good = True
    try:
        bar = tqdm(
            frames,
            total=frames.count,
            desc="track",
            unit="frame",
            disable=not progress,
            file=sys.stderr,
            leave=False,
        )
        for frame in bar:
            n += 1
            estimate: Estimate | None = None
            error = frame.error
            if frame.image is not None:
                try:
                    grey = camera.check_image(frame.image, f"{frames.description}: {frame.name}")
                    estimate = est.update(grey, frame.t_s)
                except ImageError as exc:
                    if first_good:
                        raise
                    error = str(exc)
                first_good = False
            if error:
                bad += 1
                say(error)
            writer.write(estimate_row(frame.index, frame.t_s, estimate, target, error, frame.file))
            if estimate is not None:
                valid += int(estimate.valid)
                stage_counts[estimate.stage] += 1
                total_ms += estimate.timings.total_ms
            else:
                stage_counts[0] += 1
            for hook in on_frame:
                hook(estimate, frame.t_s)
            if overlay is not None and frame.image is not None:
                if video is None:
                    h, w = frame.image.shape[:2]
                    video = OverlayWriter(overlay, frames.fps, (w, h))
                video.write(
                    draw_overlay(frame.image, estimate, camera, note=f"t {frame.t_s:.2f} s")
                )
    finally:
        writer.close()
        if video is not None:
            video.close()
    if n == 0:
        raise PerchposeError(f"{frames.description}: the source gave no frames")
    processed = max(1, n - bad)
    return TrackSummary(n, valid, bad, stage_counts, total_ms / processed, Path(out))
