"""``perchpose calibrate``: calibrate from a folder, glob or video, and write the camera file,
a short report and a coverage heat map."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from perchpose.calibration import (
    CalibrationResult,
    CharucoBoardSpec,
    calibrate,
    coverage_grid,
    select_views,
)
from perchpose.camera import DistortionModel
from perchpose.errors import CalibrationError
from perchpose.evaluation.plots import coverage_figure
from perchpose.io.sources import ImageFilesSource, open_source


@dataclass(frozen=True)
class CalibrationRun:
    """A calibration written to disk."""

    result: CalibrationResult
    camera_file: Path
    report: Path
    coverage_png: Path
    searched_frames: int


@dataclass(frozen=True)
class CalibrateOptions:
    """The images (a folder, a glob or a video), the camera file to write (.yaml), the board
    they show, the lens model, and how many views to pick out of a video."""

    source: str
    out: str
    board: CharucoBoardSpec
    model: DistortionModel = "plumb_bob"
    max_views: int = 30


def run(options: CalibrateOptions) -> CalibrationRun:
    """Calibrate from every image of a folder or glob, or from views picked out of a video;
    write ROS camera_info YAML to ``out``, ``<out>_report.md`` and ``<out>_coverage.png``."""
    source, board, model = options.source, options.board, options.model
    max_video_views = options.max_views
    out_path = Path(options.out)
    if out_path.suffix.lower() not in (".yaml", ".yml"):
        raise CalibrationError(f"{out_path}: the camera file must end in .yaml or .yml")
    frames = open_source(source)
    named = ((f.name, f.image) for f in frames if f.image is not None and not f.damaged)
    if isinstance(frames, ImageFilesSource):
        images = list(named)
        searched = len(images)
    else:
        stride = max(1, (frames.count or 0) // 300)
        images, searched = select_views(named, board, max_video_views, stride)
        if not images:
            raise CalibrationError(f"{source}: no frame of {searched} searched shows the board")
    result = calibrate(images, board, model, name=out_path.stem)
    try:
        out_path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CalibrationError(f"{out_path}: cannot make its folder ({exc.strerror})") from exc
    result.camera.save(out_path)
    stem = out_path.with_suffix("")
    coverage_png = Path(f"{stem}_coverage.png")
    size = result.camera.size
    coverage_figure(
        str(coverage_png),
        result.corners_px,
        size,
        coverage_grid(result.corners_px, size),
        f"{len(result.used)} views, {result.corners_px.shape[0]} corners, "
        f"coverage {result.coverage:.0%}",
    )
    report = Path(f"{stem}_report.md")
    report.write_text(format_report(result, board, source, searched), encoding="utf-8")
    return CalibrationRun(result, out_path, report, coverage_png, searched)


def format_report(
    result: CalibrationResult, board: CharucoBoardSpec, source: str, searched: int
) -> str:
    """The calibration report as Markdown (also printed by the command)."""
    cam = result.camera
    lines = [
        f"# Calibration of {cam.name}",
        "",
        f"Source `{source}` ({searched} frames searched); board: {board.describe()}; "
        f"model `{cam.model}`; image {cam.width_px}x{cam.height_px}.",
        "",
        f"- RMS reprojection error: **{result.rms_px:.3f} px** over {len(result.used)} views",
        f"- fx {cam.K[0, 0]:.2f}, fy {cam.K[1, 1]:.2f}, cx {cam.K[0, 2]:.2f}, "
        f"cy {cam.K[1, 2]:.2f} px",
        f"- distortion: {', '.join(f'{v:.5g}' for v in cam.dist)}",
        f"- corners cover {result.coverage:.0%} of the image (10x10 cells)",
        "",
        "| view | RMS (px) | corners left out |",
        "|---|---|---|",
        *(
            f"| {name} | {err:.3f} | {result.corners_left_out.get(name, 0)} |"
            for name, err in result.per_view_rms_px.items()
        ),
    ]
    if result.corners_left_out:
        lines += [
            "",
            f"{sum(result.corners_left_out.values())} corners were left out of the fit: their "
            "reprojection errors stood out from the other corners' (a steeply seen board pulls "
            "the corner finder).",
        ]
    if result.rejected:
        lines += ["", "Rejected:", *(f"- {k}: {v}" for k, v in result.rejected.items())]
    if result.warnings:
        lines += ["", "Warnings:", *(f"- {w}" for w in result.warnings)]
    return "\n".join(lines) + "\n"
