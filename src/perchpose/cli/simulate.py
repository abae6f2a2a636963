"""``perchpose simulate``: a rendered sequence with its truth."""

from __future__ import annotations

import click

from perchpose.cli.common import (
    board_options,
    board_spec,
    camera_option_fpv,
    quiet_option,
    show_progress,
    target_option,
)
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
@click.option("--views", default=20, show_default=True, help="board: how many views of the board.")
@board_options
@quiet_option
def simulate(
    scenario: str,
    camera_file: str,
    target_file: str | None,
    out: str,
    quality: str,
    seed: int,
    max_frames: int | None,
    views: int,
    squares: str,
    square_mm: float,
    marker_mm: float,
    dictionary: str,
    quiet: bool,
) -> None:
    """Render SCENARIO to a folder: approach or static (frames, camera.yaml, target.yaml and
    truth.csv), or board (views of the ChArUco board the board options describe and the true
    camera.yaml, to try calibrate on)."""
    from perchpose.app.simulate import BoardViewsOptions, SimulateOptions, run, run_board

    if scenario == "board":
        board = board_spec(squares, square_mm, marker_mm, dictionary)
        done = run_board(BoardViewsOptions(out, board, camera_file, views, quality, seed))
        model = f" --model {done.lens}" if done.lens != "plumb_bob" else ""
        click.echo(
            f"wrote {done.frames} views of the board and the true camera.yaml to {done.path}; "
            f"calibrate: perchpose calibrate {done.path} --out cal.yaml{model} "
            f"--squares {squares} --square-mm {square_mm:g} --marker-mm {marker_mm:g} "
            f"--dictionary {dictionary}"
        )
        return

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
