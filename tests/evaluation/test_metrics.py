import numpy as np
import pytest

from perchpose.errors import PerchposeError
from perchpose.evaluation.metrics import (
    format_stage_table,
    frame_errors,
    measurement_table,
    stage_table,
)


def _row(frame: int, valid: int, stage: int, x: float, yaw: float) -> dict[str, str]:
    v = "" if not valid else f"{x}"
    return {
        "frame": str(frame),
        "t_s": f"{frame / 30}",
        "valid": str(valid),
        "stage": str(stage),
        "x_cm": v,
        "y_cm": v,
        "z_cm": v,
        "yaw_deg": "" if not valid else f"{yaw}",
    }


def test_errors_per_frame_and_stage() -> None:
    truth = [_row(k, 1, 2, 10.0, 179.0) | {"dropout": "0"} for k in range(4)]
    track = [
        _row(0, 1, 1, 10.5, -179.0),
        _row(1, 1, 2, 9.0, 178.0),
        _row(2, 0, 0, 0, 0),
        _row(3, 1, 2, 10.0, 179.5),
    ]
    e = frame_errors(track, truth)
    assert e.valid.tolist() == [True, True, False, True]
    assert e.error_cm[0, 0] == pytest.approx(0.5)
    assert e.yaw_error_deg[0] == pytest.approx(2.0)  # -179 - 179 on the circle
    assert np.isnan(e.error_cm[2]).all()
    rows = stage_table(e)
    assert [r.stage for r in rows] == [1, 2, 0]
    assert rows[1].frames == 2
    assert rows[1].max_abs_cm[0] == pytest.approx(1.0)
    assert rows[2].median_abs_yaw_deg == pytest.approx(1.0)
    assert "2 both" in format_stage_table(rows)


def test_files_without_common_frames() -> None:
    with pytest.raises(PerchposeError, match="share no frame"):
        frame_errors([_row(5, 1, 1, 0, 0)], [_row(0, 1, 1, 0, 0)])


def test_measured_and_predicted_frames_apart() -> None:
    truth = [_row(k, 1, 2, 10.0, 0.0) | {"dropout": "0"} for k in range(4)]
    track = [
        _row(0, 1, 2, 10.1, 0.0) | {"predicted": "0"},
        _row(1, 1, 2, 10.2, 0.0) | {"predicted": "0"},
        _row(2, 1, 2, 11.0, 0.0) | {"predicted": "1"},
        _row(3, 0, 0, 0, 0) | {"predicted": ""},
    ]
    rows = measurement_table(frame_errors(track, truth))
    assert [(r.label, r.frames) for r in rows] == [("measured", 2), ("predicted", 1)]
    assert rows[1].max_abs_cm[0] == pytest.approx(1.0)
    assert "predicted" in format_stage_table(rows)
