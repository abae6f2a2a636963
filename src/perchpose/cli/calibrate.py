"""``perchpose calibrate``: a camera from ChArUco board images."""

from __future__ import annotations

import click

from perchpose.cli.common import board_options, board_spec
from perchpose.cli.group import group


@group.command()
@click.argument("source")
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(dir_okay=False),
    help="Camera file to write (ROS camera_info YAML).",
)
@board_options
@click.option(
    "--model",
    default="plumb_bob",
    show_default=True,
    type=click.Choice(["plumb_bob", "equidistant"]),
    help="Lens model: equidistant for fisheye / wide FPV lenses.",
)
@click.option("--max-views", default=30, show_default=True, help="Views to pick from a video.")
def calibrate(
    source: str,
    out: str,
    squares: str,
    square_mm: float,
    marker_mm: float,
    dictionary: str,
    model: str,
    max_views: int,
) -> None:
    """Calibrate a camera from ChArUco board images: a folder, a glob or a video."""
    from perchpose.app.calibrate import CalibrateOptions, format_report, run

    spec = board_spec(squares, square_mm, marker_mm, dictionary)
    done = run(
        CalibrateOptions(
            source,
            out,
            spec,
            "equidistant" if model == "equidistant" else "plumb_bob",
            max_views,
        )
    )
    click.echo(format_report(done.result, spec, source, done.searched_frames), nl=False)
    click.echo(f"wrote {done.camera_file}, {done.report} and {done.coverage_png}")
