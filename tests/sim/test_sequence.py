from pathlib import Path

import cv2

from perchpose import CameraModel, TargetSpec
from perchpose.io.sinks import read_track_csv
from perchpose.sim.scenarios import approach, truncated
from perchpose.sim.sequence import truth_columns, write_sequence


def test_writes_frames_camera_target_and_truth(tmp_path: Path) -> None:
    scenario = truncated(approach(dropouts=((0.1, 0.1),)), 6)
    camera = CameraModel.preset("webcam")
    out = write_sequence(scenario, camera, TargetSpec.paper(), tmp_path / "seq", progress=False)
    frames = sorted(out.glob("frame_*.png"))
    assert len(frames) == 6
    assert cv2.imread(str(frames[0]), cv2.IMREAD_UNCHANGED).shape == (480, 640)
    assert CameraModel.load(out / "camera.yaml").K[0, 0] == camera.K[0, 0]
    assert TargetSpec.load(out / "target.yaml") == TargetSpec.paper()
    rows = read_track_csv(out / "truth.csv")
    assert list(rows[0]) == list(truth_columns(TargetSpec.paper()))
    assert [r["dropout"] for r in rows] == ["0", "0", "0", "1", "1", "1"]
    assert rows[0]["stage"] == "1"  # at 1.5 m the inner marker is under 12 px
    assert rows[3]["stage"] == "0"
    assert float(rows[0]["z_cm"]) == 150.0
