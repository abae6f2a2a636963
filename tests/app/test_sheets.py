import re
from pathlib import Path

import cv2
import pytest

from perchpose.app.board import BoardOptions
from perchpose.app.board import run as run_board
from perchpose.app.target import TargetOptions
from perchpose.app.target import run as run_target
from perchpose.calibration import CharucoBoardSpec
from perchpose.errors import PerchposeError
from perchpose.target import TargetSpec


def test_target_sheet_and_its_spec(tmp_path: Path) -> None:
    sheet = run_target(
        TargetOptions(str(tmp_path / "t.svg"), save_spec=str(tmp_path / "target.yaml"))
    )
    assert sheet.path.is_file()
    assert sheet.path.read_text().lstrip().startswith("<?xml")
    assert TargetSpec.load(tmp_path / "target.yaml") == sheet.spec == TargetSpec.paper()


def test_board_sheet_and_a_refused_format(tmp_path: Path) -> None:
    board = CharucoBoardSpec((5, 7), 30.0, 15.0, "DICT_6X6_250")
    path = run_board(BoardOptions(str(tmp_path / "b.pdf"), board))
    assert path.read_bytes().startswith(b"%PDF")
    with pytest.raises(PerchposeError, match=r"b\.gif"):
        run_board(BoardOptions(str(tmp_path / "b.gif"), board))


def _media_box_mm(pdf: Path) -> tuple[float, float]:
    box = re.search(
        r"/MediaBox \[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", pdf.read_bytes().decode("latin-1")
    )
    assert box is not None
    return float(box.group(1)) / 72 * 25.4, float(box.group(2)) / 72 * 25.4


@pytest.mark.parametrize(("paper", "size_mm"), [("a4", (210.0, 297.0)), ("letter", (215.9, 279.4))])
def test_target_and_board_on_a4_and_letter_with_nothing_clipped(
    tmp_path: Path, paper: str, size_mm: tuple[float, float]
) -> None:
    """The page is the paper's, and no ink comes within 5 mm of its edges: the footer's
    text wraps inside the margins instead of running off the page."""
    board = CharucoBoardSpec((5, 7), 30.0, 15.0, "DICT_6X6_250")
    sheets = (
        run_target(TargetOptions(str(tmp_path / "t.pdf"), paper=paper)).path,
        run_board(BoardOptions(str(tmp_path / "b.pdf"), board, paper=paper)),
    )
    for pdf in sheets:
        assert _media_box_mm(pdf) == pytest.approx(size_mm, abs=0.2)
    dpi = 100
    pngs = (
        run_target(TargetOptions(str(tmp_path / "t.png"), dpi=dpi, paper=paper)).path,
        run_board(BoardOptions(str(tmp_path / "b.png"), board, dpi=dpi, paper=paper)),
    )
    edge = round(5.0 / 25.4 * dpi)
    for png in pngs:
        image = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
        # the page's pixels, as the saver truncates them
        assert image.shape == (int(size_mm[1] / 25.4 * dpi), int(size_mm[0] / 25.4 * dpi))
        ink = image < 200
        assert ink.any()
        for side in (ink[:, -edge:], ink[:, :edge], ink[-edge:, :], ink[:edge, :]):
            assert not side.any(), png


def test_a_pattern_larger_than_the_paper_is_refused_unless_fit(tmp_path: Path) -> None:
    board = CharucoBoardSpec((8, 11), 30.0, 15.0, "DICT_6X6_250")
    with pytest.raises(PerchposeError, match=r"needs a page of 260 x 380 mm, more than letter"):
        run_board(BoardOptions(str(tmp_path / "b.pdf"), board, paper="letter"))
    path = run_board(BoardOptions(str(tmp_path / "b.pdf"), board, paper="fit"))
    assert _media_box_mm(path) == pytest.approx((260.0, 380.0), abs=0.2)
