"""``perchpose bench``: what a frame costs, against OpenCV's ``detectMarkers`` and the paper's
pipeline on the same frames."""

from __future__ import annotations

import click

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
@click.option(
    "--startup",
    is_flag=True,
    help="Also time a fresh process from its start to its first pose, as a live track "
    "starts, with the compiled kernels warm (from the disk cache) and cold (compiled: "
    "about 2 minutes on 2 cores).",
)
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
    startup: bool,
    quiet: bool,
) -> None:
    """Time perchpose per frame and per stage against OpenCV's detectMarkers and the paper's
    pipeline, on one thread, on SOURCE (a folder, glob, video or camera) or a rendered
    approach; name tracking's frames over 3x its median that no loss explains; with
    --startup, the time from a process's start to its first pose."""
    from perchpose.app.bench import BenchOptions, format_report, run

    options = BenchOptions(
        source,
        camera_file,
        target_file,
        frames,
        quality,
        repeat,
        seed,
        json_out,
        plot_out,
        budget_ms,
        progress=show_progress(quiet),
        startup=startup,
    )
    report = run(options)
    click.echo(format_report(report))
    for written in (json_out, plot_out):
        if written is not None:
            click.echo(f"wrote {written}")
