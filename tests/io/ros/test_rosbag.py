"""ROS bags in: bags written by rosbags' own writers (ROS 1, ROS 2 sqlite3 and MCAP) from the
rendered approach, tracked, and compared row by row with the same frames read from files."""

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

pytest.importorskip("rosbags")

from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from perchpose import CameraModel
from perchpose.cli import main
from perchpose.io.sinks import read_track_csv

FRAMES = 12
T0_NS = 1_700_000_000_000_000_000


class Bag:
    """Writes a bag of one kind: ``ros1``, ``sqlite3`` or ``mcap``."""

    def __init__(
        self, path: Path, kind: str, frame_id: str = "camera", compression: str = ""
    ) -> None:
        self.kind = kind
        self.frame_id = frame_id
        self.ros1 = kind == "ros1"
        self.ts = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:
            self.writer: Any = Writer1(path)
            if compression:
                self.writer.set_compression(Writer1.CompressionFormat[compression.upper()])
        else:
            plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer2(path, version=9, storage_plugin=plugin)
        self.writer.open()
        self.connections: dict[str, Any] = {}

    def header(self, t_ns: int) -> Any:
        types = self.ts.types
        if self.ros1:
            stamp = types["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
            return types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=self.frame_id)
        stamp = types["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
        return types["std_msgs/msg/Header"](stamp=stamp, frame_id=self.frame_id)

    def write(self, topic: str, msg: Any, t_ns: int) -> None:
        msgtype = msg.__msgtype__
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
        data = (
            self.ts.serialize_ros1(msg, msgtype)
            if self.ros1
            else self.ts.serialize_cdr(msg, msgtype)
        )
        self.writer.write(self.connections[topic], t_ns, data)

    def image(self, topic: str, bgr: np.ndarray, encoding: str, t_ns: int) -> None:
        if encoding == "mono8":
            pixels = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
        elif encoding == "rgb8":
            pixels = bgr[:, :, ::-1]
        else:
            pixels = bgr
        channels = 1 if pixels.ndim == 2 else 3
        h, w = pixels.shape[:2]
        msg = self.ts.types["sensor_msgs/msg/Image"](
            header=self.header(t_ns),
            height=h,
            width=w,
            encoding=encoding,
            is_bigendian=0,
            step=w * channels,
            data=np.ascontiguousarray(pixels).reshape(-1),
        )
        self.write(topic, msg, t_ns)

    def compressed(self, topic: str, bgr: np.ndarray, t_ns: int) -> None:
        ok, png = cv2.imencode(".png", bgr)
        assert ok
        msg = self.ts.types["sensor_msgs/msg/CompressedImage"](
            header=self.header(t_ns), format="png", data=png.reshape(-1)
        )
        self.write(topic, msg, t_ns)

    def camera_info(self, topic: str, camera: CameraModel, t_ns: int) -> None:
        types = self.ts.types
        roi = types["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        k = camera.K.reshape(-1)
        p = np.hstack([camera.K, np.zeros((3, 1))]).reshape(-1)
        fields = {"k": k, "d": camera.dist, "r": np.eye(3).reshape(-1), "p": p}
        if self.ros1:
            fields = {key.upper(): value for key, value in fields.items()}
        msg = types["sensor_msgs/msg/CameraInfo"](
            header=self.header(t_ns),
            height=camera.height_px,
            width=camera.width_px,
            distortion_model="equidistant" if camera.model == "equidistant" else "plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=roi,
            **fields,
        )
        self.write(topic, msg, t_ns)

    def close(self) -> None:
        self.writer.close()


def _frames(folder: Path) -> list[np.ndarray]:
    return [cv2.imread(str(p)) for p in sorted(folder.glob("frame_*.png"))[:FRAMES]]


def _write(
    path: Path,
    kind: str,
    folder: Path,
    encoding: str,
    camera_info: bool = True,
    compression: str = "",
) -> Path:
    bag = Bag(path, kind, compression=compression)
    camera = CameraModel.load(folder / "camera.yaml")
    if camera_info:
        bag.camera_info("/camera/camera_info", camera, T0_NS)
    for k, bgr in enumerate(_frames(folder)):
        t_ns = T0_NS + k * 33_333_333
        if encoding == "png":
            bag.compressed("/camera/image_raw/compressed", bgr, t_ns)
        else:
            bag.image("/camera/image_raw", bgr, encoding, t_ns)
    bag.close()
    return path


@pytest.fixture(scope="module")
def reference(approach_webcam_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> list[dict]:
    """The same frames tracked from their files."""
    folder = tmp_path_factory.mktemp("first")
    for k, path in enumerate(sorted(approach_webcam_dir.glob("frame_*.png"))[:FRAMES]):
        (folder / f"frame_{k:06d}.png").write_bytes(path.read_bytes())
    out = folder / "poses.csv"
    code = main(
        ["track", str(folder), "--camera", str(approach_webcam_dir / "camera.yaml"),
         "--out", str(out), "--quiet"]
    )  # fmt: skip
    assert code == 0
    return read_track_csv(out)


@pytest.mark.parametrize(
    ("kind", "encoding", "name"),
    [
        ("sqlite3", "bgr8", "run2"),
        ("mcap", "mono8", "run_mcap"),
        ("ros1", "rgb8", "run.bag"),
        ("sqlite3", "png", "run_png"),
    ],
)
def test_a_bag_tracks_as_its_frames_do(
    approach_webcam_dir: Path,
    tmp_path: Path,
    reference: list[dict],
    kind: str,
    encoding: str,
    name: str,
) -> None:
    """One row per image message, in order, stamped from the headers, with the camera from the
    bag's CameraInfo; the poses are those of the same frames read from files (mono8: the
    same grey)."""
    bag = _write(tmp_path / name, kind, approach_webcam_dir, encoding)
    out = tmp_path / "poses.csv"
    topic = "/camera/image_raw/compressed" if encoding == "png" else "/camera/image_raw"
    code = main(["track", str(bag), "--image-topic", topic, "--out", str(out), "--quiet"])
    assert code == 0
    rows = read_track_csv(out)
    assert [int(r["frame"]) for r in rows] == list(range(FRAMES))
    for k, (row, ref) in enumerate(zip(rows, reference, strict=True)):
        assert float(row["t_s"]) == pytest.approx((T0_NS + k * 33_333_333) * 1e-9, abs=1e-6)
        assert row["file"] == f"{bag}#{topic}#{k}"
        for key in ("valid", "stage", "x_cm", "y_cm", "z_cm", "yaw_deg"):
            assert row[key] == ref[key], (k, key)


def test_a_bare_mcap_file(approach_webcam_dir: Path, tmp_path: Path) -> None:
    folder = _write(tmp_path / "run", "mcap", approach_webcam_dir, "bgr8")
    (mcap,) = folder.glob("*.mcap")
    out = tmp_path / "poses.csv"
    code = main(
        ["track", str(mcap), "--image-topic", "/camera/image_raw", "--out", str(out), "--quiet"]
    )
    assert code == 0
    assert len(read_track_csv(out)) == FRAMES


def _one_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1, err
    assert "Traceback" not in err[0]
    return err[0]


def test_bad_bags_get_one_line(
    approach_webcam_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = _write(tmp_path / "run", "sqlite3", approach_webcam_dir, "bgr8")
    out = str(tmp_path / "p.csv")
    args = ["track", str(bag), "--out", out, "--quiet"]
    assert main([*args, "--image-topic", "/nope"]) == 2
    line = _one_line(capsys)
    assert "/nope" in line
    assert "/camera/image_raw" in line  # the image topics it has
    assert main(args) == 2
    assert "--image-topic" in _one_line(capsys)
    assert main([*args, "--image-topic", "/camera/camera_info"]) == 2
    assert "CameraInfo" in _one_line(capsys)
    bare = _write(tmp_path / "bare", "sqlite3", approach_webcam_dir, "bgr8", camera_info=False)
    assert main(["track", str(bare), "--image-topic", "/camera/image_raw", "--out", out]) == 2
    assert "--camera" in _one_line(capsys)


def test_an_unsupported_encoding_keeps_the_rows_before(
    approach_webcam_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = Bag(tmp_path / "run", "sqlite3")
    camera = CameraModel.load(approach_webcam_dir / "camera.yaml")
    bag.camera_info("/camera/camera_info", camera, T0_NS)
    frames = _frames(approach_webcam_dir)
    for k in range(3):
        bag.image("/camera/image_raw", frames[k], "bgr8", T0_NS + k * 33_333_333)
    # the fourth message claims an encoding perchpose does not read: not damage, a stream
    # it cannot follow
    bag.image("/camera/image_raw", frames[3], "yuv422", T0_NS + 3 * 33_333_333)
    bag.close()
    out = tmp_path / "p.csv"
    code = main(["track", str(tmp_path / "run"), "--image-topic", "/camera/image_raw",
                 "--out", str(out), "--quiet"])  # fmt: skip
    assert code == 2
    assert "yuv422" in _one_line(capsys)
    assert len(read_track_csv(out)) == 3


def test_a_corrupt_bag_gets_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "broken.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 64)
    code = main(["track", str(bag), "--image-topic", "/camera/image_raw", "--camera",
                 "preset:webcam", "--out", str(tmp_path / "p.csv")])  # fmt: skip
    assert code == 2
    assert "broken.bag" in _one_line(capsys)


@pytest.mark.parametrize("name", ["run.mcap", "run_bag"])
def test_a_track_written_as_a_bag_reads_back_as_its_csv(
    approach_webcam_dir: Path, tmp_path: Path, name: str
) -> None:
    """The rendered approach tracked into a bag and into a CSV: read back with rosbags'
    reader, one pose (with the covariance) and one transform per valid row, equal to the CSV;
    the overlay and the row on every frame."""
    import json
    import math

    from rosbags.highlevel import AnyReader

    from perchpose.io.ros.bag_writer import OVERLAY_TOPIC, POSE_TOPIC, TF_TOPIC, TRACK_TOPIC

    folder = tmp_path / "frames"
    folder.mkdir()
    for k, path in enumerate(sorted(approach_webcam_dir.glob("frame_*.png"))[:45]):
        (folder / f"frame_{k:06d}.png").write_bytes(path.read_bytes())
    camera = str(approach_webcam_dir / "camera.yaml")
    bag, csv_out = tmp_path / name, tmp_path / "poses.csv"
    for out in (bag, csv_out):
        args = ["track", str(folder), "--camera", camera, "--out", str(out), "--quiet"]
        assert main(args) == 0
    rows = read_track_csv(csv_out)
    valid = [r for r in rows if r["valid"] == "1"]
    assert 0 < len(valid) < len(rows)  # the approach's dropout
    with AnyReader([bag]) as reader:
        by_topic: dict[str, list[Any]] = {}
        for connection, t_ns, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            by_topic.setdefault(connection.topic, []).append((t_ns, msg))
    assert len(by_topic[TRACK_TOPIC]) == len(rows)
    assert len(by_topic[OVERLAY_TOPIC]) == len(rows)
    assert len(by_topic[POSE_TOPIC]) == len(by_topic[TF_TOPIC]) == len(valid)
    for (t_ns, msg), row in zip(by_topic[POSE_TOPIC], valid, strict=True):
        assert t_ns == pytest.approx(float(row["t_s"]) * 1e9, abs=1e3)  # the CSV's 1 us
        assert msg.header.frame_id == "camera"
        p = msg.pose.pose.position
        assert [p.x * 100, p.y * 100, p.z * 100] == pytest.approx(
            [float(row[k]) for k in ("x_cm", "y_cm", "z_cm")], abs=1e-3
        )
        q = msg.pose.pose.orientation
        yaw = math.degrees(math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y**2 + q.z**2)))
        assert (yaw - float(row["yaw_deg"]) + 180) % 360 - 180 == pytest.approx(0, abs=1e-2)
        covariance = np.asarray(msg.pose.covariance).reshape(6, 6)
        assert math.sqrt(covariance[0, 0]) * 100 == pytest.approx(float(row["x_std_cm"]), rel=1e-2)
    (_, tf), *_ = by_topic[TF_TOPIC]
    assert tf.transforms[0].child_frame_id == "target"
    texts = [json.loads(m.data) for _, m in by_topic[TRACK_TOPIC]]
    assert [int(t["frame"]) for t in texts] == [int(r["frame"]) for r in rows]
    assert [t["stage"] for t in texts] == [int(r["stage"]) for r in rows]  # numbers as numbers
    predicted = [t["predicted"] for t in texts if t["valid"] == 1]
    assert predicted  # an invalid row leaves it empty
    assert all(p in (0, 1) for p in predicted)
    (_, overlay), *_ = by_topic[OVERLAY_TOPIC]
    image = cv2.imdecode(np.asarray(overlay.data, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (480, 640, 3)
    # a bag is never written over
    assert main(["track", str(folder), "--camera", camera, "--out", str(bag), "--quiet"]) == 2


def test_one_damaged_message_is_a_flagged_row_and_the_rest_are_tracked(
    approach_webcam_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A cut PNG, bytes that are no CDR and a stamp 50 ms backwards, each one message among
    eight: each is a row with its error (no pose, nothing passed to the estimator), and the
    messages after them are tracked as usual."""
    bag = Bag(tmp_path / "run", "sqlite3")
    camera = CameraModel.load(approach_webcam_dir / "camera.yaml")
    bag.camera_info("/camera/camera_info", camera, T0_NS)
    frames = _frames(approach_webcam_dir)
    topic = "/camera/image_raw/compressed"
    for k in range(8):
        t_ns = T0_NS + k * 33_333_333
        if k == 2:  # cut in half on its way to the disk
            ok, png = cv2.imencode(".png", frames[k])
            assert ok
            msg = bag.ts.types["sensor_msgs/msg/CompressedImage"](
                header=bag.header(t_ns), format="png", data=png.reshape(-1)[: png.size // 2]
            )
            bag.write(topic, msg, t_ns)
        elif k == 4:  # not the message it claims to be
            bag.writer.write(bag.connections[topic], t_ns, b"\x00\x01\x00\x00\xff\xff\xff\x7f")
        elif k == 6:  # a camera clock that stepped back; the bag's own time goes on
            ok, png = cv2.imencode(".png", frames[k])
            assert ok
            msg = bag.ts.types["sensor_msgs/msg/CompressedImage"](
                header=bag.header(t_ns - 83_333_333), format="png", data=png.reshape(-1)
            )
            bag.write(topic, msg, t_ns)
        else:
            bag.compressed(topic, frames[k], t_ns)
    bag.close()
    out = tmp_path / "p.csv"
    argv = ["track", str(tmp_path / "run"), "--image-topic", topic, "--out", str(out)]
    assert main([*argv, "--quiet"]) == 0
    err = capsys.readouterr().err
    rows = read_track_csv(out)
    assert len(rows) == 8
    flagged = {int(r["frame"]): r["error"] for r in rows if r["error"]}
    assert sorted(flagged) == [2, 4, 6]
    assert "cannot be decoded; skipped" in flagged[2]
    assert "cannot be deserialized" in flagged[4]
    assert "its stamp goes back 50.0 ms" in flagged[6]
    assert all(r["valid"] == "1" for r in rows if int(r["frame"]) in (3, 5, 7))
    assert err.count("warning:") == 3


def test_empty_huge_and_zero_size_images_are_flagged_rows(
    approach_webcam_dir: Path, tmp_path: Path, huge_png: bytes
) -> None:
    """An empty CompressedImage, one whose PNG claims 1.6 Gpx, and a 0x0 Image: each is a row
    with its reason, and the frames after them are tracked."""
    camera = CameraModel.load(approach_webcam_dir / "camera.yaml")
    frames = _frames(approach_webcam_dir)
    for topic in ("/camera/image_raw/compressed", "/camera/image_raw"):
        path = tmp_path / topic.rsplit("/", 1)[1]
        bag = Bag(path, "sqlite3")
        bag.camera_info("/camera/camera_info", camera, T0_NS)
        for k in range(5):
            t_ns = T0_NS + k * 33_333_333
            if topic.endswith("compressed") and k in (1, 2):
                data = np.frombuffer(huge_png if k == 2 else b"", np.uint8)
                msg = bag.ts.types["sensor_msgs/msg/CompressedImage"](
                    header=bag.header(t_ns), format="png", data=data
                )
                bag.write(topic, msg, t_ns)
            elif k == 1:
                msg = bag.ts.types["sensor_msgs/msg/Image"](
                    header=bag.header(t_ns), height=0, width=0, encoding="bgr8",
                    is_bigendian=0, step=0, data=np.zeros(0, np.uint8),
                )  # fmt: skip
                bag.write(topic, msg, t_ns)
            elif topic.endswith("compressed"):
                bag.compressed(topic, frames[k], t_ns)
            else:
                bag.image(topic, frames[k], "bgr8", t_ns)
        bag.close()
        out = tmp_path / f"{topic.rsplit('/', 1)[1]}.csv"
        argv = ["track", str(path), "--image-topic", topic, "--out", str(out), "--quiet"]
        assert main(argv) == 0
        rows = read_track_csv(out)
        flagged = {int(r["frame"]): r["error"] for r in rows if r["error"]}
        assert len(rows) == 5
        if topic.endswith("compressed"):
            assert sorted(flagged) == [1, 2]
            assert "the compressed image (png) is empty; skipped" in flagged[1]
            assert "CV_IO_MAX_IMAGE_PIXELS" in flagged[2]
        else:
            assert sorted(flagged) == [1]
            assert "the image is 0x0 pixels: nothing to look at; skipped" in flagged[1]
        assert all(r["valid"] == "1" for r in rows if int(r["frame"]) in (3, 4))


def _track_salvaged(
    bag: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> list[dict[str, str]]:
    """The rows of ``perchpose track`` over what a killed recorder left (warnings in
    ``caplog``); the run must end well."""
    out = tmp_path / "poses.csv"
    with caplog.at_level("WARNING", logger="perchpose.io.ros.rosbag"):
        code = main(["track", str(bag), "--image-topic", "/camera/image_raw", "--out", str(out),
                     "--quiet"])  # fmt: skip
    assert code == 0
    return read_track_csv(out)


def test_a_bare_mcap_cut_short_is_read_up_to_the_damage(
    approach_webcam_dir: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A recorder killed outright: the file stops in the middle of its messages, without the
    summary rosbags needs. Its whole messages are tracked, its CameraInfo included, and a
    warning says where it stops."""
    folder = _write(tmp_path / "run", "mcap", approach_webcam_dir, "bgr8")
    (whole,) = folder.glob("*.mcap")
    data = whole.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    rows = _track_salvaged(cut, tmp_path, caplog)
    assert 3 <= len(rows) < FRAMES
    assert all(r["valid"] == "1" for r in rows)
    assert [int(r["frame"]) for r in rows] == list(range(len(rows)))
    assert any("cut.mcap: cut short" in m for m in caplog.messages)


@pytest.mark.parametrize("metadata", [False, True])
def test_a_ros2_bag_folder_cut_short_is_read_up_to_the_damage(
    approach_webcam_dir: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture, metadata: bool
) -> None:
    """``ros2 bag record`` killed outright: its MCAP stops in the middle of its messages, and
    its folder has no metadata.yaml (written when the recorder closes), or has it from a
    recorder that wrote it before (the file still cut). The whole messages are tracked, the
    CameraInfo included, with a warning saying where it stops."""
    folder = _write(tmp_path / "run", "mcap", approach_webcam_dir, "bgr8")
    (whole,) = folder.glob("*.mcap")
    data = whole.read_bytes()
    whole.write_bytes(data[: int(len(data) * 0.6)])
    if not metadata:
        (folder / "metadata.yaml").unlink()
    rows = _track_salvaged(folder, tmp_path, caplog)
    assert 3 <= len(rows) < FRAMES
    assert all(r["valid"] == "1" for r in rows)
    assert [r["file"] for r in rows] == [
        f"{folder}#/camera/image_raw#{k}" for k in range(len(rows))
    ]
    warned = [m for m in caplog.messages if "cut short" in m]
    assert len(warned) >= 1
    assert ("no metadata.yaml" in warned[0]) is not metadata


def test_a_sqlite3_bag_its_recorder_never_closed(
    approach_webcam_dir: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """``ros2 bag record`` with sqlite3 storage (Humble's default) killed outright: its .db3
    whole (SQLite's own journal keeps it so) but no metadata.yaml. Every message is tracked in
    order, CameraInfo included, with a warning; a .db3 cut short is one line (SQLite refuses
    the whole file)."""
    folder = _write(tmp_path / "run", "sqlite3", approach_webcam_dir, "bgr8")
    (folder / "metadata.yaml").unlink()
    rows = _track_salvaged(folder, tmp_path, caplog)
    assert len(rows) == FRAMES
    assert all(r["valid"] == "1" for r in rows)
    assert [float(r["t_s"]) for r in rows] == pytest.approx(
        [(T0_NS + k * 33_333_333) * 1e-9 for k in range(FRAMES)], abs=1e-6
    )
    assert any("no metadata.yaml" in m for m in caplog.messages)
    (db3,) = folder.glob("*.db3")
    data = db3.read_bytes()
    db3.write_bytes(data[: int(len(data) * 0.6)])
    out = tmp_path / "poses.csv"
    code = main(["track", str(folder), "--image-topic", "/camera/image_raw", "--out", str(out),
                 "--quiet"])  # fmt: skip
    assert code == 2


@pytest.mark.parametrize("compression", ["", "bz2", "lz4"])
def test_a_ros1_bag_cut_short_is_read_up_to_the_damage(
    approach_webcam_dir: Path,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    reference: list[dict],
    compression: str,
) -> None:
    """``rosbag record`` killed outright: the bag stops in its chunks, before the index that
    rosbags reads first. The messages of its whole chunks (and of a plain chunk the cut went
    through) are tracked in order, stamped from their headers, CameraInfo included, each the
    same pose as its frame read from its file."""
    bag = _write(tmp_path / "run.bag", "ros1", approach_webcam_dir, "rgb8", compression=compression)
    data = bag.read_bytes()
    bag.write_bytes(data[: int(len(data) * 0.6)])
    rows = _track_salvaged(bag, tmp_path, caplog)
    assert 3 <= len(rows) < FRAMES
    for k, (row, ref) in enumerate(zip(rows, reference[: len(rows)], strict=True)):
        assert float(row["t_s"]) == pytest.approx((T0_NS + k * 33_333_333) * 1e-9, abs=1e-6)
        for key in ("valid", "stage", "x_cm", "y_cm", "z_cm", "yaw_deg"):
            assert row[key] == ref[key], (k, key)
    assert any("run.bag: cut short" in m for m in caplog.messages)


def test_a_split_bag_left_unclosed_is_read_file_after_file(
    approach_webcam_dir: Path, tmp_path: Path
) -> None:
    """Two MCAP files of one recording (``run_0``, ``run_1``: a recorder splitting its bag),
    the second cut, no metadata.yaml: the first file's frames then the second's, in order."""
    first = _write(tmp_path / "a", "mcap", approach_webcam_dir, "bgr8")
    second = _write(tmp_path / "b", "mcap", approach_webcam_dir, "bgr8", camera_info=False)
    folder = tmp_path / "run"
    folder.mkdir()
    (part0,) = first.glob("*.mcap")
    (part1,) = second.glob("*.mcap")
    data = part1.read_bytes()
    (folder / "run_0.mcap").write_bytes(part0.read_bytes())
    (folder / "run_1.mcap").write_bytes(data[: int(len(data) * 0.6)])
    out = tmp_path / "poses.csv"
    code = main(["track", str(folder), "--image-topic", "/camera/image_raw", "--out", str(out),
                 "--quiet"])  # fmt: skip
    assert code == 0
    rows = read_track_csv(out)
    assert FRAMES + 3 <= len(rows) < 2 * FRAMES
    assert all(r["valid"] == "1" for r in rows[1:FRAMES])


def test_a_folder_of_images_beside_an_mcap_is_read_as_images(
    approach_webcam_dir: Path, tmp_path: Path
) -> None:
    """A track written as run.mcap into the folder of the frames it read: the folder is still
    read as images."""
    from perchpose.io.ros.rosbag import is_bag

    folder = tmp_path / "frames"
    folder.mkdir()
    (folder / "frame_000000.png").write_bytes(
        (approach_webcam_dir / "frame_000000.png").read_bytes()
    )
    (folder / "run.mcap").write_bytes(b"")
    assert not is_bag(str(folder))
    (folder / "frame_000000.png").unlink()
    assert is_bag(str(folder))


@pytest.mark.parametrize(
    ("frames_args", "camera_frame", "target_frame"),
    [
        ((), "camera_optical_frame", "target"),
        (("--camera-frame", "cam", "--target-frame", "plate"), "cam", "plate"),
    ],
)
def test_every_output_carries_its_image_s_exact_stamp_and_frame(
    approach_webcam_dir: Path,
    tmp_path: Path,
    frames_args: tuple[str, ...],
    camera_frame: str,
    target_frame: str,
) -> None:
    """Stamps 1700000000.123456789 s + k/30 s (not a float's worth of nanoseconds) and the
    image's frame id come back exactly on every pose, transform, overlay and row of the bag
    written; --camera-frame and --target-frame name them instead."""
    from rosbags.highlevel import AnyReader

    from perchpose.io.ros.bag_writer import OVERLAY_TOPIC, POSE_TOPIC, TF_TOPIC, TRACK_TOPIC

    source = Bag(tmp_path / "in.mcap", "mcap", frame_id="camera_optical_frame")
    stamps = [T0_NS + 123_456_789 + k * 33_333_333 for k in range(FRAMES)]
    for t_ns, bgr in zip(stamps, _frames(approach_webcam_dir), strict=True):
        source.image("/camera/image_raw", bgr, "bgr8", t_ns)
    source.close()
    out = tmp_path / "run.mcap"
    camera = str(approach_webcam_dir / "camera.yaml")
    args = ["track", str(tmp_path / "in.mcap"), "--image-topic", "/camera/image_raw"]
    assert main([*args, "--camera", camera, "--out", str(out), "--quiet", *frames_args]) == 0
    with AnyReader([out]) as reader:
        by_topic: dict[str, list[Any]] = {}
        for connection, t_ns, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            by_topic.setdefault(connection.topic, []).append((t_ns, msg))
    assert [t_ns for t_ns, _ in by_topic[TRACK_TOPIC]] == stamps
    assert len(by_topic[POSE_TOPIC]) > FRAMES // 2
    for topic in (POSE_TOPIC, OVERLAY_TOPIC):
        for t_ns, msg in by_topic[topic]:
            header_ns = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert header_ns == t_ns
            assert t_ns in stamps
            assert msg.header.frame_id == camera_frame
    for t_ns, tf in by_topic[TF_TOPIC]:
        (transform,) = tf.transforms
        assert transform.header.frame_id == camera_frame
        assert transform.child_frame_id == target_frame
        assert transform.header.stamp.sec * 10**9 + transform.header.stamp.nanosec == t_ns
