"""The ROS 2 node (``perchpose ros2``) against a real rclpy camera in another process."""

from __future__ import annotations

import json
import math
import os
import random
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from perchpose.errors import PerchposeError
from perchpose.io.ros.node import LatestImage, NodeSettings, NodeStats, _typed
from perchpose.io.sinks import read_track_csv
from perchpose.values import Estimate

CAMERA = Path(__file__).with_name("ros2_camera.py")
FRAMES = 16


def test_the_newest_image_replaces_one_that_waits() -> None:
    slot = LatestImage()
    assert slot.put("a", 0.0) is False
    assert slot.put("b", 1.0) is True  # "a" was never taken: dropped
    assert slot.take(0.0) == ("b", 1.0)
    assert slot.take(0.0) is None
    slot.close()
    assert slot.take(10.0) is None  # closed: no wait


def test_diagnostics_say_what_happened_and_start_a_new_period() -> None:
    stats = NodeStats()
    for _ in range(3):
        stats.count("received")
    stats.count("dropped")
    stats.took(Estimate.none(0.0), 0.020)
    level, message, values = stats.report("")
    assert (level, message) == (1, "no target in view")
    assert values["dropped"] == "1"
    assert values["stage_0"] == "1"
    assert float(values["latency_p95_ms"]) == pytest.approx(20.0)
    assert stats.report("camera_info")[:2] == (1, "waiting for camera_info")
    assert stats.report("")[2]["dropped"] == "0"


def test_parameters_are_checked_by_name() -> None:
    assert _typed("budget_ms", 20, 0.0) == 20.0
    with pytest.raises(PerchposeError, match="parameter budget_ms: a number"):
        _typed("budget_ms", "fast", 0.0)
    with pytest.raises(PerchposeError, match="parameter publish_overlay: true or false"):
        _typed("publish_overlay", 1, False)
    with pytest.raises(PerchposeError, match="image_transport"):
        NodeSettings(image_transport="theora")
    assert set(NodeSettings.defaults()) == set(NodeSettings.__dataclass_fields__)


def _ros_env() -> dict[str, str]:
    return os.environ | {
        "ROS_DOMAIN_ID": str(random.Random().randint(1, 100)),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
    }


def _fly(
    frames: Path,
    tmp_path: Path,
    node_args: list[str],
    camera_args: list[str],
    qos_overrides: bool = True,
) -> tuple[dict, str]:
    """Run the node and the camera; what the camera heard, and the node's log.
    ``qos_overrides``: the image subscription told to be reliable by parameter (else the node
    matches the camera's publisher by itself)."""
    env = _ros_env()
    remaps = ["-r", "camera_info:=/cam/camera_info"]
    for topic in ("image_raw", "image_raw/compressed"):
        remaps += ["-r", f"{topic}:=/cam/{topic}"]
        if qos_overrides:
            remaps += ["-p", f"qos_overrides./cam/{topic}.subscription.reliability:=reliable"]
    node = subprocess.Popen(
        [sys.executable, "-m", "perchpose", "ros2", "--ros-args", *remaps, *node_args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    out = tmp_path / "heard.json"
    try:
        subprocess.run(
            [sys.executable, str(CAMERA), str(frames), str(FRAMES), str(out), *camera_args],
            env=env,
            check=True,
            timeout=400,
        )
    finally:
        node.terminate()
        log, _ = node.communicate(timeout=30)
    return json.loads(out.read_text()), log


@pytest.mark.slow  # the node fed 90 frames in a ROS 2 graph (about 16 s)
def test_every_pose_has_its_image_s_exact_stamp_and_frame_and_matches_the_truth(
    approach_webcam_dir: Path, tmp_path: Path
) -> None:
    pytest.importorskip("rclpy")
    heard, log = _fly(
        approach_webcam_dir, tmp_path, ["-p", "target_frame:=plate"], [], qos_overrides=False
    )
    # the camera publishes reliable: the node subscribes so, as ros2 topic echo would
    assert "/cam/image_raw: 1 publisher(s), reliable: subscribed reliable" in log, log
    sent, poses, tracks = heard["sent"], heard["poses"], heard["tracks"]
    assert sent[0] % 10**9 == 123_456_789  # not a float's worth of nanoseconds
    assert {t["stamp_ns"] for t in tracks} == set(sent), log
    assert all(t["frame_id"] == "camera_optical_frame" for t in tracks)
    assert len(poses) >= FRAMES - 1  # the first frames at 1.5 m: every one has a pose
    truth = {
        sent[k]: row
        for k, row in enumerate(read_track_csv(approach_webcam_dir / "truth.csv")[:FRAMES])
    }
    for pose in poses:
        assert pose["frame_id"] == "camera_optical_frame"
        row = truth[pose["stamp_ns"]]
        xyz_cm = np.array(pose["xyz"]) * 100
        assert xyz_cm == pytest.approx([float(row[k]) for k in ("x_cm", "y_cm", "z_cm")], abs=2.0)
        x, y, z, w = pose["q"]
        yaw = math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
        assert (yaw - float(row["yaw_deg"]) + 180) % 360 - 180 == pytest.approx(0, abs=2.0)
        covariance = np.array(pose["covariance"]).reshape(6, 6)
        assert np.all(np.linalg.eigvalsh(covariance) > 0)
    reports = [d for d in heard["diagnostics"] if d["name"] == "perchpose: target pose"]
    assert reports
    assert sum(int(d["values"]["stage_1"]) + int(d["values"]["stage_2"]) for d in reports) > 0
    assert all(d["level"] == 0 for d in reports if d["values"]["rate_hz"] != "0.00")


def test_a_compressed_image_of_another_size_is_refused_with_a_log_and_the_rest_tracked(
    approach_webcam_dir: Path, tmp_path: Path
) -> None:
    pytest.importorskip("rclpy")
    heard, log = _fly(
        approach_webcam_dir,
        tmp_path,
        ["-p", "camera_frame:=cam", "-p", "image_transport:=compressed"],
        ["--odd-size", "3", "--compressed"],
    )
    stamps = {t["stamp_ns"] for t in heard["tracks"]}
    assert heard["sent"][3] not in stamps
    assert set(heard["sent"]) - stamps == {heard["sent"][3]}
    assert all(p["frame_id"] == "cam" for p in heard["poses"])
    assert len(heard["poses"]) >= FRAMES - 2
    refusals = [line for line in log.splitlines() if "refused" in line]
    assert len(refusals) == 1
    assert "320x240" in refusals[0]
    reports = heard["diagnostics"]
    assert sum(int(d["values"]["refused"]) for d in reports) == 1  # sent once
    assert [d["message"] for d in reports if d["level"] == 2] == ["1 image refused (see the log)"]


def test_a_refused_camera_info_is_in_the_diagnostics_until_a_good_one_replaces_it() -> None:
    """fx of a billionth of a pixel is no camera: refused, and the diagnostics say why while
    the node waits; the next good camera_info is taken."""
    rclpy = pytest.importorskip("rclpy")
    from perchpose.io.ros.node import NodeSettings, PoseNode, _ros

    ros = _ros()
    rclpy.init(args=[])
    try:
        node = rclpy.create_node("perchpose_info_test")
        pose_node = PoseNode(ros, node, NodeSettings())
        info = ros["sensor"].CameraInfo(width=640, height=480, distortion_model="plumb_bob")
        info.d = [0.0] * 5
        info.k = [1e-9, 0.0, 320.0, 0.0, 400.0, 240.0, 0.0, 0.0, 1.0]
        pose_node._on_camera_info(info)
        assert pose_node.camera is None
        assert pose_node.waiting_for().startswith("camera_info (the last refused: ")
        assert "fx = 1e-09 px is under a pixel" in pose_node.waiting_for()
        info.k = [400.0, 0.0, 320.0, 0.0, 400.0, 240.0, 0.0, 0.0, 1.0]
        pose_node._on_camera_info(info)
        assert pose_node.camera is not None
        assert pose_node.waiting_for() == ""
        pose_node.close()
        node.destroy_node()
    finally:
        rclpy.shutdown()


def test_a_camera_whose_stamps_start_over_is_followed_with_one_warning(
    approach_webcam_dir: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """Frames stamped 100.0, 100.033, 100.067 s, then 5.0 s (a driver that restarted): the
    fourth is tracked, tracking starting over, with one warning; a frame 10 ms behind the one
    before it is refused as out of order, not taken for a restart."""
    rclpy = pytest.importorskip("rclpy")
    import cv2

    from perchpose.io.ros.node import NodeSettings, PoseNode, _ros

    ros = _ros()
    rclpy.init(args=[])
    try:
        node = rclpy.create_node("perchpose_stamps_test")
        settings = NodeSettings(camera_file=str(approach_webcam_dir / "camera.yaml"))
        pose_node = PoseNode(ros, node, settings)
        frames = sorted(approach_webcam_dir.glob("frame_*.png"))

        def image(k: int, t_s: float) -> object:
            grey = cv2.imread(str(frames[k]), cv2.IMREAD_GRAYSCALE)
            msg = ros["sensor"].Image(
                height=grey.shape[0], width=grey.shape[1], encoding="mono8", step=grey.shape[1]
            )
            msg.data = grey.tobytes()
            msg.header.stamp.sec = int(t_s)
            msg.header.stamp.nanosec = round((t_s % 1) * 1e9)
            msg.header.frame_id = "camera_optical_frame"
            return msg

        for k, t_s in enumerate((100.0, 100.033, 100.067, 5.0, 4.99, 5.033)):
            pose_node._process(image(k, t_s), time.monotonic())
        assert pose_node.stats.total_taken == 5
        assert pose_node.stats.refused == 1
        assert pose_node.last_stamp_s == pytest.approx(5.033)
        log = capfd.readouterr().err
        assert log.count("the stamps went back 95.1 s") == 1
        assert "a stamp 10.0 ms behind the one before; refused" in log
        pose_node.close()
        node.destroy_node()
    finally:
        rclpy.shutdown()


def test_without_rclpy_the_error_says_what_to_do_on_this_python() -> None:
    """The 'ros2' extra installs nothing outside Python 3.11 on Linux: there the error says
    to source a ROS 2 install, not to install the extra just installed."""
    from perchpose.io.ros.node import missing_rclpy

    elsewhere = missing_rclpy("rclpy", (3, 12), "linux")
    assert "Python 3.12 on linux" in elsewhere
    assert "install nothing" in elsewhere
    assert "pip install" not in elsewhere
    assert "pip install 'perchpose[ros2]'" in missing_rclpy("rclpy", (3, 11), "linux")
    assert "install nothing on Python 3.11 on darwin" in missing_rclpy("rclpy", (3, 11), "darwin")
