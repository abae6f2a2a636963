"""``perchpose board``: a printable ChArUco calibration board at true scale."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from perchpose.calibration import CharucoBoardSpec


@dataclass(frozen=True)
class BoardOptions:
    """The board and where to write it (.svg, .pdf or .png at ``dpi``), on ``paper``
    (``a4``, ``letter`` or ``fit``)."""

    out: str
    board: CharucoBoardSpec
    dpi: int = 600
    paper: str = "a4"


def run(options: BoardOptions) -> Path:
    """Write the board sheet; its path."""
    from perchpose.printable import write_board_sheet

    return write_board_sheet(options.board, options.out, dpi=options.dpi, paper=options.paper)
