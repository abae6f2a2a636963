"""``perchpose simulate``: a rendered sequence with its truth."""

from __future__ import annotations

import click

from perchpose.cli.common import camera_option_fpv, quiet_option, show_progress, target_option
from perchpose.cli.group import group


@group.command()
@click.argument("scenario")
@camera_option_fpv
@target_option
@click.option(
    "--out", "out", required=True, type=click.Path(file_okay=False), help="Output folder."
)
@click.option(
    "--quality",
    default="default",
    show_default=True,
    type=click.Choice(["clean", "default", "analog_fpv"]),
    help="Image degradation.",
)
@click.option("--seed", default=0, show_default=True, help="Noise seed.")
@click.option(
    "--frames", "max_frames", default=None, type=int, help="Keep only the first N frames."
)
@quiet_option
def simulate(
    scenario: str,
    camera_file: str,
    target_file: str | None,
    out: str,
    quality: str,
    seed: int,
    max_frames: int | None,
    quiet: bool,
) -> None:
    """Render SCENARIO (approach or static) to frames, camera.yaml and truth.csv."""
    from perchpose.app.simulate import SimulateOptions, run

    options = SimulateOptions(
        scenario,
        out,
        camera_file,
        target_file,
        quality,
        seed,
        max_frames,
        progress=show_progress(quiet),
    )
    written = run(options)
    click.echo(f"wrote {written.frames} frames, camera.yaml and truth.csv to {written.path}")
