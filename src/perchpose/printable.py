"""Printable sheets at true scale: the target and the calibration board (SVG, PDF or PNG) with a
100 mm scale bar, on A4, Letter or a page their own size."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Polygon, Rectangle

from perchpose.calibration import CharucoBoardSpec
from perchpose.errors import PerchposeError
from perchpose.target import TargetSpec

MM_PER_INCH = 25.4
SHEET_MARGIN_MM = 10.0
SCALE_BAR_MM = 100.0
FOOTER_MM = 30.0  # under the pattern: the scale bar and what the sheet is
FOOTER_PT = 5.5
FOOTER_CHAR_MM = 1.25  # wider than the widest average character of the footer's font, mm
FORMATS = (".svg", ".pdf", ".png")
PAPERS = {"a4": (210.0, 297.0), "letter": (215.9, 279.4)}  # (width, height), mm
PAPER_NAMES = ("a4", "letter", "fit")  # fit: a page the pattern's own size


def page_size_mm(pattern_mm: tuple[float, float], paper: str, what: str) -> tuple[float, float]:
    """(width, height) of the page for a pattern ``pattern_mm`` wide and high with its margins
    and footer: the paper's, or for ``fit`` just enough; PerchposeError naming ``what`` when
    it does not fit on the paper, or for an unknown paper."""
    w_mm, h_mm = pattern_mm
    need = (
        max(w_mm, SCALE_BAR_MM + 20.0) + 2 * SHEET_MARGIN_MM,
        h_mm + 2 * SHEET_MARGIN_MM + FOOTER_MM,
    )
    if paper == "fit":
        return need
    if paper not in PAPERS:
        raise PerchposeError(f"--paper: unknown {paper!r} (choose {', '.join(PAPER_NAMES)})")
    width, height = PAPERS[paper]
    if need[0] > width or need[1] > height:
        raise PerchposeError(
            f"{what} needs a page of {need[0]:.0f} x {need[1]:.0f} mm, more than {paper} "
            f"({width:g} x {height:g} mm): --paper fit writes a page its own size, to print on "
            "a larger sheet"
        )
    return width, height


def draw_footer(ax: Axes, page_mm: tuple[float, float], bar_y_mm: float, text: str) -> None:
    """The 100 mm scale bar centred at ``bar_y_mm`` and ``text`` under it, wrapped to the
    page's width inside its margins."""
    width = page_mm[0]
    draw_scale_bar(ax, width / 2 - SCALE_BAR_MM / 2 - 10.0, bar_y_mm)
    usable_mm = width - 2 * SHEET_MARGIN_MM
    wrapped = textwrap.fill(text, width=max(20, int(usable_mm / FOOTER_CHAR_MM)))
    ax.text(SHEET_MARGIN_MM, bar_y_mm + 6.0, wrapped, fontsize=FOOTER_PT, va="top")


def check_output_format(path: Path) -> str:
    """The output suffix, or PerchposeError if it is not SVG, PDF or PNG."""
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise PerchposeError(f"{path}: output must end in .svg, .pdf or .png")
    return suffix


def draw_scale_bar(ax: Axes, x0_mm: float, y0_mm: float) -> None:
    """A 100 mm bar with 10 mm ticks at (x0, y0) of a millimetre, y-down axes."""
    ax.add_patch(Rectangle((x0_mm, y0_mm), SCALE_BAR_MM, 2.0, color="black", lw=0))
    for k in range(11):
        x = x0_mm + 10.0 * k
        tick = 4.0 if k % 5 == 0 else 2.5
        ax.plot([x, x], [y0_mm, y0_mm - tick], color="black", lw=0.5)
    ax.text(x0_mm + SCALE_BAR_MM + 3.0, y0_mm + 1.0, "100 mm", fontsize=7, va="center")


def new_sheet(width_mm: float, height_mm: float) -> tuple[Figure, Axes]:
    """A figure exactly ``width_mm`` x ``height_mm`` with one full-size axes in millimetres
    (origin top-left, y down)."""
    fig = Figure(figsize=(width_mm / MM_PER_INCH, height_mm / MM_PER_INCH))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(0.0, width_mm)
    ax.set_ylim(height_mm, 0.0)
    ax.set_axis_off()
    return fig, ax


def save_sheet(fig: Figure, path: Path, dpi: int) -> None:
    """Save at true scale; PNG at ``dpi``."""
    try:
        fig.savefig(path, dpi=dpi, facecolor="white")
    except OSError as exc:
        raise PerchposeError(f"{path}: cannot write ({exc.strerror})") from exc


def write_target_sheet(
    target: TargetSpec, path: str | Path, dpi: int = 600, paper: str = "a4"
) -> Path:
    """Write ``target`` as a printable sheet on ``paper`` (``PAPER_NAMES``); the format
    follows the suffix (.svg .pdf .png)."""
    out = Path(path)
    check_output_format(out)
    _check_dpi(dpi)
    side_mm = 2000.0 * target.sheet_half_extent_m
    width, height = sheet_size_mm(target, paper)
    fig, ax = new_sheet(width, height)
    cx = width / 2.0
    cy = SHEET_MARGIN_MM + side_mm / 2.0
    ax.add_patch(
        Rectangle(
            (cx - side_mm / 2, cy - side_mm / 2),
            side_mm,
            side_mm,
            fill=False,
            edgecolor="#bbbbbb",
            lw=0.3,
        )
    )
    for m in target.markers:
        n = m.cells.shape[0]
        cell = m.side_mm / n
        T = m.T_target_marker
        # white background of the marker, then its black cells, so markers printed over others
        # keep their own white cells
        for r in range(n):
            for c in range(n):
                x0 = -m.side_mm / 2 + c * cell
                y0 = m.side_mm / 2 - r * cell
                corners = np.array(
                    [[x0, y0], [x0 + cell, y0], [x0 + cell, y0 - cell], [x0, y0 - cell]]
                )
                pts = (T[:2, :2] @ corners.T).T + 1000.0 * T[:2, 3]
                sheet = np.stack([cx + pts[:, 0], cy - pts[:, 1]], axis=1)
                colour = "white" if m.cells[r, c] else "black"
                ax.add_patch(
                    Polygon(
                        sheet,
                        closed=True,
                        facecolor=colour,
                        edgecolor="none",
                    )
                )
    markers = "; ".join(f"{m.dictionary} id {m.marker_id} {m.side_mm:g} mm" for m in target.markers)
    draw_footer(
        ax,
        (width, height),
        cy + side_mm / 2 + 12.0,
        f"perchpose target '{target.name}': {markers}. Print at 100 % (no fit to page): the "
        "bar is 100 mm.",
    )
    save_sheet(fig, out, dpi)
    return out


def _check_dpi(dpi: int) -> None:
    if not 72 <= dpi <= 2400:
        raise PerchposeError(f"--dpi must be between 72 and 2400, got {dpi}")


def sheet_size_mm(target: TargetSpec, paper: str = "a4") -> tuple[float, float]:
    """(width, height) of the sheet ``write_target_sheet`` draws on ``paper``, millimetres."""
    side_mm = 2000.0 * target.sheet_half_extent_m
    return page_size_mm((side_mm, side_mm), paper, f"the target '{target.name}'")


def board_sheet_size_mm(board: CharucoBoardSpec, paper: str = "a4") -> tuple[float, float]:
    """(width, height) of the sheet ``write_board_sheet`` draws on ``paper``, millimetres."""
    sx, sy = board.squares
    pattern = (sx * board.square_mm, sy * board.square_mm)
    return page_size_mm(pattern, paper, f"the board ({board.describe()})")


__all__ = [
    "PAPER_NAMES",
    "board_sheet_size_mm",
    "sheet_size_mm",
    "write_board_sheet",
    "write_target_sheet",
]


def write_board_sheet(
    board: CharucoBoardSpec, path: str | Path, dpi: int = 600, paper: str = "a4"
) -> Path:
    """Write a ChArUco board at true scale on ``paper`` with its parameters and a 100 mm
    scale bar."""
    out = Path(path)
    check_output_format(out)
    _check_dpi(dpi)
    sx, sy = board.squares
    w_mm, h_mm = sx * board.square_mm, sy * board.square_mm
    width, height = board_sheet_size_mm(board, paper)
    fig, ax = new_sheet(width, height)
    x0 = (width - w_mm) / 2.0
    y0 = SHEET_MARGIN_MM
    for r in range(sy):
        for c in range(sx):
            if (r + c) % 2 == 0:  # OpenCV's layout: the top-left square is black
                ax.add_patch(
                    Rectangle(
                        (x0 + c * board.square_mm, y0 + r * board.square_mm),
                        board.square_mm,
                        board.square_mm,
                        facecolor="black",
                        edgecolor="none",
                    )
                )
    dictionary = board.cv_board.getDictionary()
    cells_n = int(dictionary.markerSize) + 2
    cell = board.marker_mm / cells_n
    for marker_id, corners in zip(
        np.asarray(board.cv_board.getIds()).reshape(-1), board.cv_board.getObjPoints(), strict=True
    ):
        top_left = np.asarray(corners, np.float64)[0, :2] * 1000.0
        bits = dictionary.generateImageMarker(int(marker_id), cells_n, borderBits=1) > 127
        for r in range(cells_n):
            for c in range(cells_n):
                if not bits[r, c]:
                    ax.add_patch(
                        Rectangle(
                            (x0 + top_left[0] + c * cell, y0 + top_left[1] + r * cell),
                            cell,
                            cell,
                            facecolor="black",
                            edgecolor="none",
                        )
                    )
    draw_footer(
        ax,
        (width, height),
        y0 + h_mm + 12.0,
        f"perchpose calibration board: {board.describe()}. Print at 100 % (no fit to page): "
        "the bar is 100 mm. Any scale works: measure a square and give its side as "
        "--square-mm.",
    )
    save_sheet(fig, out, dpi)
    return out
