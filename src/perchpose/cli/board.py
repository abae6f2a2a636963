"""``perchpose board``: a printable ChArUco calibration board."""

from __future__ import annotations

import click

from perchpose.cli.common import (
    board_options,
    board_spec,
    dpi_option,
    paper_option,
    sheet_out_option,
)
from perchpose.cli.group import group


@group.command()
@sheet_out_option
@board_options
@dpi_option
@paper_option
def board(
    out: str,
    squares: str,
    square_mm: float,
    marker_mm: float,
    dictionary: str,
    dpi: int,
    paper: str,
) -> None:
    """Write a printable ChArUco calibration board at true scale."""
    from perchpose.app.board import BoardOptions, run

    spec = board_spec(squares, square_mm, marker_mm, dictionary)
    path = run(BoardOptions(out, spec, dpi, paper))
    click.echo(f"wrote {path} ({spec.describe()}): print at 100 % and glue it flat")
