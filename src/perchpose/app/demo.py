"""The embedded demo: render an approach with dropouts, track it, compare with the truth."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from perchpose.app.inputs import load_camera
from perchpose.app.track import TrackSummary, track
from perchpose.camera import CameraModel
from perchpose.estimator import PerchingEstimator
from perchpose.evaluation.metrics import (
    FrameErrors,
    StageRow,
    frame_errors,
    measurement_table,
    stage_table,
)
from perchpose.evaluation.plots import kalman_figure
from perchpose.io.sinks import read_track_csv
from perchpose.sim.scenarios import approach
from perchpose.sim.sequence import write_sequence
from perchpose.target import TargetSpec


@dataclass(frozen=True)
class DemoOptions:
    """The output folder, the camera as the commands name it, the approach's length and the
    noise seed."""

    out: str
    camera_file: str = "preset:fpv"
    seconds: float = 8.0
    seed: int = 0
    progress: bool = False


@dataclass(frozen=True)
class DemoResult:
    """Where the demo wrote its files, and what it measured."""

    out_dir: Path
    summary: TrackSummary
    errors: FrameErrors
    table: list[StageRow]
    coasted_valid_frames: int
    figure: Path
    overlay: Path


def _series(rows: list[dict[str, str]], keys: tuple[str, ...]) -> np.ndarray:
    return np.array([[float(r[k]) if r.get(k) else math.nan for k in keys] for r in rows])


def run_demo(
    out_dir: str | Path,
    camera: CameraModel | None = None,
    duration_s: float = 8.0,
    seed: int = 0,
    progress: bool = True,
    say: Callable[[str], None] = print,
) -> DemoResult:
    """Render an approach from 150 cm to contact (yaw across +/-180 deg, two dropouts), track it
    with overlay, and write ``poses.csv``, ``overlay.mp4`` and ``kalman.png`` into ``out_dir``."""
    out = Path(out_dir)
    cam = camera or CameraModel.preset("fpv")
    target = TargetSpec.paper()
    scenario = approach(duration_s=duration_s)
    frames_dir = out / "frames"
    say(
        f"rendering {len(scenario)} frames of an approach through camera '{cam.name}' "
        f"into {frames_dir}"
    )
    write_sequence(scenario, cam, target, frames_dir, seed=seed, progress=progress)
    say("tracking")
    poses = out / "poses.csv"
    overlay = out / "overlay.mp4"
    summary = track(
        str(frames_dir),
        PerchingEstimator(cam, target),
        poses,
        fps=30.0,
        overlay=overlay,
        progress=progress,
    )
    track_rows = read_track_csv(poses)
    truth_rows = read_track_csv(frames_dir / "truth.csv")
    errors = frame_errors(track_rows, truth_rows)
    # by stage, all valid frames, then measured frames against the filter's predictions
    table = stage_table(errors) + measurement_table(errors)
    coasted = int(np.count_nonzero(errors.valid & errors.dropout))
    raw = {
        target.marker_name(i): _series(
            track_rows, (f"m{i}_x_cm", f"m{i}_y_cm", f"m{i}_z_cm", f"m{i}_yaw_deg")
        )
        for i in range(len(target.markers))
    }
    figure = out / "kalman.png"
    keys = ("x_cm", "y_cm", "z_cm", "yaw_deg")
    kalman_figure(
        str(figure),
        errors.t_s,
        raw,
        _series(track_rows, keys),
        _series(truth_rows, keys),
        errors.dropout,
        f"Raw per-marker poses and the filtered estimate ({cam.name} camera)",
    )
    return DemoResult(out, summary, errors, table, coasted, figure, overlay)


def run(options: DemoOptions, say: Callable[[str], None] = print) -> DemoResult:
    """The demo as ``perchpose demo`` runs it (``run_demo``)."""
    return run_demo(
        options.out,
        load_camera(options.camera_file),
        duration_s=options.seconds,
        seed=options.seed,
        progress=options.progress,
        say=say,
    )
