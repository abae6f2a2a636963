import json
from pathlib import Path

import numpy as np
import pytest

from perchpose import PerchingEstimator, TargetSpec
from perchpose.errors import PerchposeError
from perchpose.geometry import facing_pose
from perchpose.io.sinks import BASE_COLUMNS, PoseWriter, columns, estimate_row, read_track_csv
from perchpose.sim.render import Renderer


def _estimate(r: Renderer):  # type: ignore[no-untyped-def]
    est = PerchingEstimator(r.camera, r.target)
    return est.update(r.render(facing_pose(0.01, 0.02, 0.5, 0.4), rng=np.random.default_rng(0)), 0)


def test_csv_rows_hold_pose_and_raw_measurements(
    tmp_path: Path, renderers: dict[str, Renderer]
) -> None:
    r = renderers["webcam"]
    target = TargetSpec.paper()
    e = _estimate(r)
    with PoseWriter(tmp_path / "p.csv", target) as w:
        w.write(estimate_row(0, 0.0, e, target))
        w.write(estimate_row(1, 1 / 30, None, target, error="1.png: cannot read image"))
    rows = read_track_csv(tmp_path / "p.csv")
    assert tuple(rows[0])[: len(BASE_COLUMNS)] == BASE_COLUMNS
    assert tuple(rows[0]) == columns(target)
    assert rows[0]["valid"] == "1"
    assert float(rows[0]["z_cm"]) == pytest.approx(50.0, abs=0.5)
    assert float(rows[0]["m0_z_cm"]) == pytest.approx(50.0, abs=0.5)
    assert float(rows[0]["m1_yaw_deg"]) == pytest.approx(np.degrees(0.4), abs=3)
    assert rows[1]["valid"] == "0"
    assert rows[1]["x_cm"] == ""
    assert rows[1]["error"] == "1.png: cannot read image"


def test_jsonl(tmp_path: Path, renderers: dict[str, Renderer]) -> None:
    r = renderers["webcam"]
    target = TargetSpec.paper()
    with PoseWriter(tmp_path / "p.jsonl", target) as w:
        w.write(estimate_row(0, 0.0, _estimate(r), target))
        w.write(estimate_row(1, 0.5, None, target))
    lines = [json.loads(s) for s in (tmp_path / "p.jsonl").read_text().splitlines()]
    assert lines[0]["valid"] == 1
    assert lines[0]["z_cm"] == pytest.approx(50.0, abs=0.5)
    assert lines[1]["x_cm"] is None


def test_bad_output_suffix(tmp_path: Path) -> None:
    with pytest.raises(PerchposeError, match=r"\.csv or \.jsonl"):
        PoseWriter(tmp_path / "p.txt", TargetSpec.paper())
