"""``perchpose fit-fusion``: the fusion sigmas from labelled data."""

from __future__ import annotations

import click

from perchpose.cli.common import warn
from perchpose.cli.group import group


@group.command(name="fit-fusion")
@click.argument("data", type=click.Path(dir_okay=False))
@click.option(
    "--truth",
    "truth_file",
    default=None,
    type=click.Path(dir_okay=False),
    help="truth.csv of the frames, when DATA is a track file.",
)
@click.option(
    "--json",
    "json_out",
    default=None,
    type=click.Path(dir_okay=False),
    help="Also write the fitted weights as JSON (for track --sigmas).",
)
def fit_fusion(data: str, truth_file: str | None, json_out: str | None) -> None:
    """Fit the fusion sigmas from labelled data (least squares and the paper's LMS).

    DATA has columns true_x_cm, true_y_cm, true_z_cm, true_yaw_deg and each marker's raw
    measurement m0_* (outer) and m1_* (inner); or it is a track file and --truth gives the
    truth.csv of the same frames."""
    from perchpose.app.fit_fusion import FitFusionOptions, run
    from perchpose.evaluation.experiments import COMPONENT_NAMES, PAPER_SIGMAS

    fitted = run(FitFusionOptions(data, truth_file, json_out))
    result = fitted.fit
    click.echo(f"{result.samples} frames with truth and both markers (weights held to [0, 1])")
    click.echo(f"{'':10} {'least sq.':>10} {'LMS':>10} {'paper':>10}")
    for name in COMPONENT_NAMES:
        click.echo(
            f"{name:10} {result.least_squares[name]:10.3f} {result.lms[name]:10.3f} "
            f"{PAPER_SIGMAS[name]:10.3f}"
        )
    rms = fitted.samples.rms_errors()
    for name in result.at_bounds:
        unit = "deg" if name == "sigma_yaw" else "cm"
        outer, inner = rms[name]
        alone = "outer" if result.least_squares[name] > 0.5 else "inner"
        warn(
            f"fit-fusion: {name} sits at its bound ({result.least_squares[name]:.3f}): on these "
            f"frames the {alone} marker alone does best (rms error outer {outer:.4f} {unit}, "
            f"inner {inner:.4f} {unit}), so with these weights the paper's fusion takes the "
            f"{alone} marker's pose wherever both are seen; the default fusion (no --sigmas) "
            "weighs the markers frame by frame by their covariance and needs no fit"
        )
    if json_out:
        click.echo(f"wrote {json_out}: use it with 'perchpose track ... --sigmas {json_out}'")
