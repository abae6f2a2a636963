"""``perchpose target``: the printable target."""

from __future__ import annotations

import click

from perchpose.cli.common import dpi_option, paper_option, sheet_out_option, target_option
from perchpose.cli.group import group


@group.command()
@sheet_out_option
@target_option
@dpi_option
@paper_option
@click.option(
    "--save-spec",
    default=None,
    type=click.Path(dir_okay=False),
    help="Also write the target's YAML specification here.",
)
def target(out: str, target_file: str | None, dpi: int, paper: str, save_spec: str | None) -> None:
    """Write the printable target at true scale, with a 100 mm scale bar."""
    from perchpose.app.target import TargetOptions, run

    sheet = run(TargetOptions(out, target_file, dpi, save_spec, paper))
    click.echo(f"wrote {sheet.path}: print at 100 % and check that the scale bar measures 100 mm")
