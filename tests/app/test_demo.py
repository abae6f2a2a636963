from pathlib import Path

import numpy as np
import pytest

from perchpose import CameraModel
from perchpose.app.demo import run_demo
from perchpose.evaluation.metrics import format_stage_table


@pytest.mark.slow  # the README's demo, whole (about 7 s)
def test_demo_writes_its_files_and_measures(tmp_path: Path) -> None:
    messages: list[str] = []
    result = run_demo(
        tmp_path / "demo",
        CameraModel.preset("webcam"),
        duration_s=3.0,
        progress=False,
        say=messages.append,
    )
    assert messages
    for name in ("poses.csv", "overlay.mp4", "kalman.png", "frames/truth.csv"):
        assert (tmp_path / "demo" / name).stat().st_size > 0
    table = format_stage_table(result.table)
    assert "all" in table
    assert result.summary.frames == 90
    # the 0.2 s dropout (6 frames) is bridged entirely; 0.5 s of the second is past 3 s
    assert result.coasted_valid_frames == int(result.errors.dropout.sum()) == 6
    assert np.median(np.abs(result.errors.error_cm[result.errors.valid]), axis=0).max() < 0.5
