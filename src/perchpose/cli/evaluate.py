"""``perchpose evaluate``: the paper's experiments."""

from __future__ import annotations

import click

from perchpose.cli.common import camera_option_fpv, quiet_option, show_progress
from perchpose.cli.group import group


@group.command()
@click.argument("experiment", type=click.Choice(["paper"]))
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(file_okay=False),
    help="Output folder for report.md, results.json and the figures.",
)
@camera_option_fpv
@click.option(
    "--quality",
    default="analog_fpv",
    show_default=True,
    type=click.Choice(["clean", "default", "analog_fpv"]),
    help="Image degradation for the tables, the dropout, the fit and the ablations.",
)
@click.option("--quick", is_flag=True, help="A reduced run (under a minute) for smoke tests.")
@click.option("--seed", default=0, show_default=True, help="Base seed of every experiment.")
@quiet_option
def evaluate(
    experiment: str, out: str, camera_file: str, quality: str, quick: bool, seed: int, quiet: bool
) -> None:
    """Reproduce the paper's experiments (EXPERIMENT: paper) on rendered frames."""
    from perchpose.app.evaluate import EvaluateOptions, run

    options = EvaluateOptions(
        out, experiment, camera_file, quality, quick, seed, progress=show_progress(quiet)
    )
    result = run(options, say=lambda msg: click.echo(msg, err=True))
    r = result.results
    ranges = r["ranges"]
    click.echo(
        f"ranges ({ranges['quality']} images): outer up to "
        f"{ranges['outer']['z_max_cm']} cm, inner up to {ranges['inner']['z_max_cm']} cm"
    )
    if r["fusion_fit"] is not None:
        ls = r["fusion_fit"]["least_squares"]
        click.echo(
            "fusion fit (least squares): " + ", ".join(f"{k} {v:.3f}" for k, v in ls.items())
        )
    click.echo(f"wrote {result.report}, {result.out_dir / 'results.json'} and figures")
