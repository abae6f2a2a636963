import json
from pathlib import Path

import numpy as np
import pytest

from perchpose import PerchingEstimator, TargetSpec
from perchpose.errors import PerchposeError
from perchpose.geometry import facing_pose
from perchpose.io.sinks import PoseWriter, columns, estimate_row, read_track_csv
from perchpose.sim.render import Renderer
from perchpose.values import POSE_COLUMNS


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
    assert tuple(rows[0])[: len(POSE_COLUMNS)] == POSE_COLUMNS
    assert tuple(rows[0]) == columns(target)
    assert rows[0]["valid"] == "1"
    assert float(rows[0]["z_cm"]) == pytest.approx(50.0, abs=0.5)
    assert float(rows[0]["m0_z_cm"]) == pytest.approx(50.0, abs=0.5)
    assert float(rows[0]["m1_yaw_deg"]) == pytest.approx(np.degrees(0.4), abs=3)
    assert rows[1]["valid"] == "0"
    assert rows[1]["x_cm"] == ""
    assert rows[1]["error"] == "1.png: cannot read image"
    # the whole pose and its uncertainty: a target facing the camera has no tilt
    assert float(rows[0]["roll_deg"]) == pytest.approx(0.0, abs=0.5)
    assert float(rows[0]["pitch_deg"]) == pytest.approx(0.0, abs=0.5)
    x_std, _, z_std, yaw_std = e.std
    assert float(rows[0]["x_std_cm"]) == pytest.approx(x_std * 100, rel=1e-2)
    assert float(rows[0]["z_std_cm"]) == pytest.approx(z_std * 100, rel=1e-2)
    assert float(rows[0]["yaw_std_deg"]) == pytest.approx(np.degrees(yaw_std), rel=1e-2)
    assert rows[1]["roll_deg"] == rows[1]["x_std_cm"] == ""


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
    with pytest.raises(PerchposeError, match=r"\.csv, \.jsonl or \.mcap"):
        PoseWriter(tmp_path / "p.txt", TargetSpec.paper())


class _FillingDisk:
    """The file object of a disk that fills up: it takes ``room`` more characters, writes part
    of the next text and then fails as a full disk does."""

    def __init__(self, inner, room: int) -> None:  # type: ignore[no-untyped-def]
        self.inner = inner
        self.room = room

    def write(self, text: str) -> int:
        if len(text) > self.room:
            self.inner.write(text[: self.room // 2 + 1])
            self.inner.flush()
            raise OSError(28, "No space left on device")
        self.room -= len(text)
        return int(self.inner.write(text))

    def flush(self) -> None:
        self.inner.flush()

    def tell(self) -> int:
        return int(self.inner.tell())

    def close(self) -> None:
        self.inner.close()


def test_a_full_disk_keeps_whole_rows_and_names_the_file(tmp_path: Path) -> None:
    target = TargetSpec.paper()
    path = tmp_path / "p.csv"
    writer = PoseWriter(path, target)
    for k in range(3):
        writer.write(estimate_row(k, k / 30, None, target, error="x", file=f"{k}.png"))
    writer._file = _FillingDisk(writer._file, room=20)  # type: ignore[assignment]
    full = r"p\.csv: cannot write \(No space left on device\); 3 whole rows kept"
    with pytest.raises(PerchposeError, match=full):
        writer.write(estimate_row(3, 3 / 30, None, target, error="x", file="3.png"))
    writer.close()
    rows = read_track_csv(path)
    assert [r["frame"] for r in rows] == ["0", "1", "2"]
    assert all(r["file"] == f"{k}.png" for k, r in enumerate(rows))
    assert path.read_text().endswith("\n")


def test_rows_reach_the_file_as_they_are_written(tmp_path: Path) -> None:
    """A run killed at any point (SIGKILL included) keeps every row written before it."""
    target = TargetSpec.paper()
    writer = PoseWriter(tmp_path / "p.csv", target)
    for k in range(5):
        writer.write(estimate_row(k, k / 30, None, target))
    assert len(read_track_csv(tmp_path / "p.csv")) == 5  # before close
    writer.close()
