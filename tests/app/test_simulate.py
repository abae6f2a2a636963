import csv
from pathlib import Path

import pytest

from perchpose.app.simulate import SimulateOptions, run
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
