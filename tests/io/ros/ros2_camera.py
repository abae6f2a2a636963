"""A camera as a ROS 2 process (for tests/io/ros/test_node.py): publishes a rendered sequence's
frames as sensor_msgs/Image with CameraInfo, one at a time, each once the node has answered
the one before on /perchpose/track (sent again each second until it does), and writes what
came back on /perchpose/pose and /perchpose/track to a JSON file.

    python ros2_camera.py FRAMES_DIR COUNT OUT_JSON [--odd-size K] [--compressed]
                          [--frame-id F] [--t0-ns N]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import String


def _camera_info(camera_yaml: Path, frame_id: str) -> CameraInfo:
    data = yaml.safe_load(camera_yaml.read_text())
    info = CameraInfo()
    info.header.frame_id = frame_id
    info.width, info.height = int(data["image_width"]), int(data["image_height"])
    info.distortion_model = str(data["distortion_model"])
    info.k = [float(v) for v in data["camera_matrix"]["data"]]
    info.d = [float(v) for v in data["distortion_coefficients"]["data"]]
    return info


class Camera:
    """The camera node: publishes frames and hears what perchpose says back."""

    def __init__(self, frames: Path, frame_id: str, compressed: bool) -> None:
        self.node = rclpy.create_node("fake_camera")
        self.compressed = compressed
        # reliable, as many drivers publish: a best-effort image of 0.9 MB loses fragments
        # over UDP here more often than not
        self.images = (
            self.node.create_publisher(CompressedImage, "/cam/image_raw/compressed", 5)
            if compressed
            else self.node.create_publisher(Image, "/cam/image_raw", 5)
        )
        self.infos = self.node.create_publisher(CameraInfo, "/cam/camera_info", 5)
        self.info = _camera_info(frames / "camera.yaml", frame_id)
        self.frame_id = frame_id
        self.poses: list[dict[str, object]] = []
        self.tracks: list[dict[str, object]] = []
        self.node.create_subscription(
            PoseWithCovarianceStamped, "/perchpose/pose", self._on_pose, 50
        )
        self.node.create_subscription(String, "/perchpose/track", self._on_track, 50)
        self.diagnostics: list[dict[str, object]] = []
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)

    def _on_pose(self, msg: PoseWithCovarianceStamped) -> None:
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        self.poses.append(
            {
                "stamp_ns": msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec,
                "frame_id": msg.header.frame_id,
                "xyz": [p.x, p.y, p.z],
                "q": [q.x, q.y, q.z, q.w],
                "covariance": [float(v) for v in msg.pose.covariance],
            }
        )

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            self.diagnostics.append(
                {"name": status.name, "level": status.level[0], "message": status.message}
                | {"values": values}
            )

    def _on_track(self, msg: String) -> None:
        self.tracks.append(json.loads(msg.data))

    def spin_for(self, seconds: float, until: object = None) -> bool:
        """Spin up to ``seconds``; True as soon as a track row of stamp ``until`` came."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            rclpy.spin_once(self.node, timeout_sec=0.01)
            if until is not None and any(t.get("stamp_ns") == until for t in self.tracks):
                return True
        return False

    def wait_for_the_node(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while self.images.get_subscription_count() == 0 and time.monotonic() < end:
            rclpy.spin_once(self.node, timeout_sec=0.05)

    def send(self, bgr: np.ndarray, t_ns: int, answer_s: float) -> None:
        """Publish one frame (with its CameraInfo) each second until it is answered."""
        msg: Image | CompressedImage
        if self.compressed:
            msg = CompressedImage(format="png")
            msg.data = cv2.imencode(".png", bgr)[1].tobytes()
        else:
            msg = Image(height=bgr.shape[0], width=bgr.shape[1], encoding="bgr8")
            msg.step = bgr.shape[1] * 3
            msg.data = np.ascontiguousarray(bgr).tobytes()
        msg.header.frame_id = self.frame_id
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_ns, 10**9)
        self.info.header.stamp = msg.header.stamp
        give_up = time.monotonic() + answer_s
        while time.monotonic() < give_up:
            self.infos.publish(self.info)
            self.images.publish(msg)
            if self.spin_for(min(1.0, give_up - time.monotonic()), until=t_ns):
                return


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("frames", type=Path)
    parser.add_argument("count", type=int)
    parser.add_argument("out", type=Path)
    parser.add_argument("--frame-id", default="camera_optical_frame")
    parser.add_argument("--t0-ns", type=int, default=1_700_000_000_123_456_789)
    parser.add_argument("--odd-size", type=int, default=-1, help="this frame is sent half size")
    parser.add_argument("--compressed", action="store_true", help="PNG CompressedImage")
    args = parser.parse_args()
    rclpy.init()
    camera = Camera(args.frames, args.frame_id, args.compressed)
    camera.wait_for_the_node(120.0)
    sent = []
    for k, path in enumerate(sorted(args.frames.glob("frame_*.png"))[: args.count]):
        bgr = cv2.imread(str(path))
        if k == args.odd_size:
            bgr = cv2.resize(bgr, (bgr.shape[1] // 2, bgr.shape[0] // 2))
        t_ns = args.t0_ns + k * 33_333_333
        sent.append(t_ns)
        # the first frame may compile the fits; a refused one is never answered
        camera.send(bgr, t_ns, 0.5 if k == args.odd_size else 120.0 if k == 0 else 20.0)
    camera.spin_for(1.0)
    camera.spin_for(1.5)  # a last diagnostics period
    result = {
        "sent": sent,
        "poses": camera.poses,
        "tracks": camera.tracks,
        "diagnostics": camera.diagnostics,
    }
    args.out.write_text(json.dumps(result))
    camera.node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
