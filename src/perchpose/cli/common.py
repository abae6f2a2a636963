"""What the commands share: their options, whether to show a progress bar, and a warning line
on stderr (``app.inputs`` loads the camera and target they name)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import TYPE_CHECKING

import click

if TYPE_CHECKING:
    from perchpose.calibration import CharucoBoardSpec


def warn(message: str) -> None:
    """One line on stderr."""
    click.echo(f"perchpose: {message}", err=True)


CAMERA_HELP = "ROS camera_info or OpenCV YAML; or preset:webcam, preset:fpv, preset:fpv_wide"
target_option = click.option(
    "--target", "target_file", default=None, help="Target YAML (default: the paper's)."
)
quiet_option = click.option("--quiet", is_flag=True, help="No progress bar.")
# a printable sheet (the target, a calibration board): where, and a PNG's resolution
sheet_out_option = click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(dir_okay=False),
    help="Output file: .svg, .pdf or .png.",
)
dpi_option = click.option("--dpi", default=600, show_default=True, help="Resolution of a PNG.")
paper_option = click.option(
    "--paper",
    default="a4",
    show_default=True,
    type=click.Choice(["a4", "letter", "fit"]),
    help="The page: A4 (210 x 297 mm), Letter (8.5 x 11 in) or fit (a page the pattern's own "
    "size, for a larger sheet).",
)


def budget_option(help_text: str) -> Callable[[Callable[..., None]], Callable[..., None]]:
    """``--budget-ms``: a positive time budget per frame, milliseconds."""
    return click.option(
        "--budget-ms",
        default=None,
        type=click.FloatRange(min=0.0, min_open=True),
        help=help_text,
    )


def show_progress(quiet: bool) -> bool:
    """A progress bar unless ``--quiet`` or stderr is not a terminal."""
    return not quiet and sys.stderr.isatty()


camera_option_fpv = click.option(
    "--camera", "camera_file", default="preset:fpv", show_default=True, help=CAMERA_HELP
)


def board_options(command: Callable[..., None]) -> Callable[..., None]:
    """The ChArUco board options shared by ``board`` and ``calibrate``."""
    options = [
        click.option(
            "--squares", default="5x7", show_default=True, help="Squares across x down, e.g. 5x7."
        ),
        click.option(
            "--square-mm",
            default=30.0,
            show_default=True,
            help="Side of a square, mm (measure the print).",
        ),
        click.option("--marker-mm", default=15.0, show_default=True, help="Side of a marker, mm."),
        click.option(
            "--dictionary",
            default="DICT_6X6_250",
            show_default=True,
            help="OpenCV ArUco dictionary of the markers.",
        ),
    ]
    for option in reversed(options):
        command = option(command)
    return command


def board_spec(
    squares: str, square_mm: float, marker_mm: float, dictionary: str
) -> CharucoBoardSpec:
    """The board the ``board_options`` describe (imported late: OpenCV's ArUco module)."""
    from perchpose.calibration import CharucoBoardSpec

    return CharucoBoardSpec(
        CharucoBoardSpec.parse_squares(squares), square_mm, marker_mm, dictionary
    )
