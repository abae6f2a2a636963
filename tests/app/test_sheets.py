from pathlib import Path

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
