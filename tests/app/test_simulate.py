import csv
from pathlib import Path

import pytest

from perchpose.app.simulate import BoardViewsOptions, SimulateOptions, run, run_board
from perchpose.calibration import CharucoBoardSpec
from perchpose.camera import CameraModel
from perchpose.cli import main
from perchpose.errors import PerchposeError


def test_a_short_sequence_with_its_truth(tmp_path: Path) -> None:
    written = run(SimulateOptions("approach", str(tmp_path / "seq"), max_frames=3))
    assert written.frames == 3
    assert len(sorted(written.path.glob("frame_*.png"))) == 3
    assert (written.path / "camera.yaml").is_file()
    with open(written.path / "truth.csv", newline="") as f:
        assert len(list(csv.DictReader(f))) == 3


def test_an_unknown_scenario_is_named(tmp_path: Path) -> None:
    with pytest.raises(PerchposeError, match="orbit"):
        run(SimulateOptions("orbit", str(tmp_path / "seq")))


def test_board_views_calibrate_to_the_camera_that_rendered_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``simulate board`` then ``calibrate`` as its last line says: the calibration finds the
    true camera (written beside the views) within 1 %."""
    out = tmp_path / "views"
    argv = ["simulate", "board", "--out", str(out), "--views", "14", "--camera", "preset:webcam"]
    assert main(argv) == 0
    said = capsys.readouterr().out
    assert len(sorted(out.glob("view_*.png"))) == 14
    command = said.split("calibrate: perchpose ")[1].split()
    assert "--model" not in command  # the webcam is a plumb_bob lens, calibrate's default
    assert main([*command[:2], "--out", str(tmp_path / "cal.yaml"), *command[4:]]) == 0
    truth = CameraModel.load(out / "camera.yaml")
    found = CameraModel.load(tmp_path / "cal.yaml")
    for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)):
        assert found.K[i, j] == pytest.approx(truth.K[i, j], rel=0.01)


def test_board_views_bad_count(tmp_path: Path) -> None:
    board = CharucoBoardSpec()
    with pytest.raises(PerchposeError, match="--views must be 1 to 500, got 0"):
        run_board(BoardViewsOptions(str(tmp_path / "v"), board, views=0))
