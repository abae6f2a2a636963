"""``perchpose bench``: what a frame costs, against OpenCV's ``detectMarkers`` and the paper's
pipeline on the same frames."""

from __future__ import annotations

import json
from pathlib import Path

import click

from perchpose.app.inputs import load_camera, load_target
from perchpose.cli.common import (
    CAMERA_HELP,
    budget_option,
    quiet_option,
    show_progress,
    target_option,
)
from perchpose.cli.group import group

QUALITIES = ("default", "clean", "analog_fpv", "harsh")


@group.command()
@click.argument("source", required=False)
@click.option(
    "--camera",
    "camera_file",
    default="preset:fpv",
    show_default=True,
    help=f"{CAMERA_HELP}. Required with a SOURCE.",
)
@target_option
@click.option(
    "--frames",
    default=240,
    show_default=True,
    help="Frames to render, or the most to read from SOURCE.",
)
@click.option(
    "--quality",
    type=click.Choice(QUALITIES),
    default="default",
    show_default=True,
    help="Image quality of the rendered approach (without SOURCE).",
)
@click.option(
    "--repeat",
    default=3,
    show_default=True,
    help="Runs over the frames; each frame's time is the least of them.",
)
@click.option("--seed", default=0, show_default=True, help="Noise seed of the rendered frames.")
@click.option(
    "--json",
    "json_out",
    default=None,
    type=click.Path(dir_okay=False),
    help="Also write the report as JSON.",
)
@click.option(
    "--plot",
    "plot_out",
    default=None,
    type=click.Path(dir_okay=False),
    help="Also draw it frame by frame: times, stages, errors (.png, .svg or .pdf).",
)
@budget_option("Also time perchpose within this budget per frame (perchpose-budget).")
@quiet_option
def bench(
    source: str | None,
    camera_file: str,
    target_file: str | None,
    frames: int,
    quality: str,
    repeat: int,
    seed: int,
    json_out: str | None,
    plot_out: str | None,
    budget_ms: float | None,
    quiet: bool,
) -> None:
    """Time perchpose per frame and per stage against OpenCV's detectMarkers and the paper's
    pipeline, on one thread, on SOURCE (a folder, glob, video or camera) or a rendered
    approach."""
    from perchpose.app.bench import bench as run_bench
    from perchpose.app.bench import (
        default_methods,
        format_report,
        rendered_frames,
        source_frames,
        write_figure,
    )
    from perchpose.errors import PerchposeError
    from perchpose.printable import check_output_format
    from perchpose.sim.render import ImageQuality

    if source is not None and camera_file.startswith("preset:"):
        raise PerchposeError("a SOURCE needs its calibration: --camera camera.yaml")
    if plot_out is not None:
        check_output_format(Path(plot_out))  # before the run, not after it
    camera = load_camera(camera_file)
    target = load_target(target_file)
    progress = show_progress(quiet)
    if source is None:
        data = rendered_frames(camera, target, frames, ImageQuality.preset(quality), seed, progress)
    else:
        data = source_frames(source, camera, frames)
    report = run_bench(
        data,
        camera,
        target,
        repeat,
        progress,
        lambda cam, spec: default_methods(cam, spec, budget_ms),
    )
    click.echo(format_report(report))
    if json_out is not None:
        path = Path(json_out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(report.to_json(), indent=2) + "\n")
        click.echo(f"wrote {path}")
    if plot_out is not None:
        Path(plot_out).parent.mkdir(parents=True, exist_ok=True)
        write_figure(report, plot_out)
        click.echo(f"wrote {plot_out}")
