"""``perchpose demo``: a rendered approach tracked and compared with its truth."""

from __future__ import annotations

import click

from perchpose.cli.common import camera_option_fpv, quiet_option, show_progress
from perchpose.cli.group import group


@group.command()
@click.option(
    "--out",
    "out",
    default="perchpose-demo",
    show_default=True,
    type=click.Path(file_okay=False),
    help="Output folder.",
)
@camera_option_fpv
@click.option("--seconds", default=8.0, show_default=True, help="Length of the approach.")
@click.option("--seed", default=0, show_default=True, help="Noise seed.")
@quiet_option
def demo(out: str, camera_file: str, seconds: float, seed: int, quiet: bool) -> None:
    """Render an approach with dropouts, track it and compare with the truth."""
    from perchpose.app.demo import DemoOptions, run
    from perchpose.evaluation.metrics import format_stage_table

    options = DemoOptions(out, camera_file, seconds, seed, progress=show_progress(quiet))
    result = run(options, say=click.echo)
    click.echo("")
    click.echo(format_stage_table(result.table))
    click.echo("")
    dropouts = int(result.errors.dropout.sum())
    click.echo(
        f"dropout frames: {dropouts}, of which {result.coasted_valid_frames} were bridged "
        f"by the filter (at most 8 in a row stay valid)"
    )
    click.echo(f"wrote {result.out_dir / 'poses.csv'}, {result.overlay}, {result.figure}")
