"""``perchpose simulate``: a rendered sequence with its truth."""

from __future__ import annotations

import click

from perchpose.app.inputs import load_camera, load_target
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
    from perchpose.sim.render import ImageQuality
    from perchpose.sim.scenarios import scenario_by_name, truncated
    from perchpose.sim.sequence import write_sequence

    cam = load_camera(camera_file)
    spec = load_target(target_file)
    scen = scenario_by_name(scenario, ImageQuality.preset(quality))
    if max_frames is not None:
        scen = truncated(scen, max_frames)
    path = write_sequence(scen, cam, spec, out, seed=seed, progress=show_progress(quiet))
    click.echo(f"wrote {len(scen)} frames, camera.yaml and truth.csv to {path}")
