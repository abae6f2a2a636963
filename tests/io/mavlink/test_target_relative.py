"""TARGET_RELATIVE from pymavlink's generator, sent beside LANDING_TARGET and decoded on
loopback by the generated dialect."""

import math
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from perchpose.cli import main
from perchpose.control import downward_T_body_camera
from perchpose.errors import LinkError
from perchpose.io.mavlink.landing_target import R_ned_frd_from_euler
from perchpose.io.mavlink.landing_target_sink import LandingTargetSink
from perchpose.io.mavlink.target_relative import dialect, target_relative
from perchpose.io.sinks import read_track_csv
from perchpose.values import Estimate

DOWN = downward_T_body_camera()
# standard deviations in the camera frame: x 2 mm, y 3 mm, z 7 mm; rotations 0.01, 0.02, 0.05
SIGMAS = np.array([0.002, 0.003, 0.007, 0.01, 0.02, 0.05])


def with_covariance(t_s: float, xyz_m: tuple[float, float, float], yaw_rad: float) -> Estimate:
    estimate = Estimate.of_pose(t_s, xyz_m, yaw_rad, stage=1)
    C = np.diag(SIGMAS**2)
    return replace(estimate, covariance_flat=tuple(float(v) for v in C.ravel()))


def test_the_generated_message_is_the_published_one() -> None:
    """Id 511, 71 bytes, and the CRC extra of MAVLink's development dialect (28): a vehicle
    built from the published definition decodes what we send."""
    module = dialect()
    cls = module.MAVLink_target_relative_message
    assert module.MAVLINK_MSG_ID_TARGET_RELATIVE == 511
    assert cls.crc_extra == 28
    assert cls.unpacker.size == 71


def test_standard_deviations_follow_the_frame() -> None:
    """The downward camera's x is the body's right and its y the body's back: in FRD the
    standard deviations of x and y swap, z stays; in the vehicle's NED at yaw 90 degrees they
    swap back; yaw_std is the rotation's about the optical axis."""
    estimate = with_covariance(1.0, (0.05, -0.02, 0.8), 0.3)
    frd = target_relative(estimate, DOWN)
    assert frd.pos_std_m == pytest.approx((0.003, 0.002, 0.007))
    assert frd.yaw_std_rad == pytest.approx(0.05)
    assert frd.q_sensor_wxyz == (0.0, 0.0, 0.0, 0.0)  # no attitude: ignored
    assert frd.timestamp_usec == 1_000_000
    R = R_ned_frd_from_euler(0.0, 0.0, math.pi / 2)
    ned = target_relative(estimate, DOWN, frame="local_ned", R_ned_frd=R)
    assert ned.pos_std_m == pytest.approx((0.002, 0.003, 0.007))
    assert [ned.x_m, ned.y_m, ned.z_m] == pytest.approx(R @ [frd.x_m, frd.y_m, frd.z_m])
    with pytest.raises(LinkError, match="no covariance"):
        target_relative(Estimate.of_pose(1.0, (0.0, 0.0, 0.5), 0.0), DOWN)
    with pytest.raises(LinkError, match="ATTITUDE"):
        target_relative(estimate, DOWN, frame="local_ned")


def test_sent_beside_landing_target_and_decoded_by_the_published_definition() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as vehicle:
        vehicle.bind(("127.0.0.1", 0))
        vehicle.settimeout(0.05)
        port = vehicle.getsockname()[1]
        reports: list[str] = []
        sink = LandingTargetSink(
            f"udpout:127.0.0.1:{port}",
            T_body_camera=DOWN,
            target_relative=True,
            timesync_period_s=0.0,
            report=reports.append,
        )
        try:
            assert sink.send(with_covariance(0.5, (0.05, -0.02, 0.8), 0.3))
            assert sink.send(Estimate.of_pose(0.6, (0.0, 0.0, 0.5), 0.0))  # no covariance
            received = receive(vehicle, 1.0)
        finally:
            sink.close()
    parser = dialect().MAVLink(None)
    parser.robust_parsing = True
    decoded = [m for m in parser.parse_buffer(received) or [] if m.get_type() == "TARGET_RELATIVE"]
    assert len(decoded) == 1  # the second estimate has no covariance: LANDING_TARGET only
    (msg,) = decoded
    assert msg.get_srcComponent() == 191  # the link's own ids and sequence
    assert msg.frame == 1  # TARGET_OBS_FRAME_BODY_FRD
    assert msg.type == 2  # VISION_FIDUCIAL
    assert msg.timestamp == 500_000
    assert list(msg.pos_std) == pytest.approx([0.003, 0.002, 0.007], rel=1e-6)
    assert msg.yaw_std == pytest.approx(0.05, rel=1e-6)
    expected = target_relative(with_covariance(0.5, (0.05, -0.02, 0.8), 0.3), DOWN)
    assert [msg.x, msg.y, msg.z] == pytest.approx([expected.x_m, expected.y_m, expected.z_m])
    assert list(msg.q_target) == pytest.approx(list(expected.q_target_wxyz), abs=1e-6)
    assert sum("no covariance" in r for r in reports) == 1


def receive(sock: socket.socket, seconds: float) -> bytes:
    data = b""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            data += sock.recv(65536)
        except TimeoutError:
            continue
    return data


def test_track_sends_one_per_valid_row(
    approach_fpv_dir: Path, tmp_path: Path, track_argv: Callable[..., list[str]]
) -> None:
    """Through the CLI: each valid frame's covariance goes out as TARGET_RELATIVE, its
    standard deviations the track file's own (a downward camera: x and y swap in FRD)."""
    out = tmp_path / "poses.csv"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as vehicle:
        vehicle.bind(("127.0.0.1", 0))
        vehicle.settimeout(0.05)
        received = bytearray()
        done = threading.Event()

        def collect() -> None:
            while not done.is_set():
                received.extend(receive(vehicle, 0.1))

        collector = threading.Thread(target=collect)
        collector.start()
        try:
            code = main(
                track_argv(
                    approach_fpv_dir,
                    out,
                    "--quiet",
                    "--mavlink",
                    f"udpout:127.0.0.1:{vehicle.getsockname()[1]}",
                    "--mount",
                    "down",
                    "--mavlink-target-relative",
                )
            )
            time.sleep(0.3)
        finally:
            done.set()
            collector.join()
    assert code == 0
    parser = dialect().MAVLink(None)
    parser.robust_parsing = True
    messages = parser.parse_buffer(bytes(received)) or []
    decoded = [m for m in messages if m.get_type() == "TARGET_RELATIVE"]
    rows = [r for r in read_track_csv(out) if r["valid"] == "1"]
    assert len(decoded) == len(rows) > 0
    for row, msg in zip(rows, decoded, strict=True):
        std_cm = [float(row[k]) for k in ("x_std_cm", "y_std_cm", "z_std_cm")]
        assert [v * 100 for v in msg.pos_std] == pytest.approx(
            [std_cm[1], std_cm[0], std_cm[2]], rel=1e-3, abs=1e-4
        )


def test_no_code_is_imported_from_the_shared_temporary_folder(tmp_path: Path) -> None:
    """A module another local user planted where the dialect used to be cached (a predictable
    folder under the system's temporary directory) never runs; the dialect is generated in a
    private folder, run from memory, and nothing is left behind."""
    planted = tmp_path / "ran"
    code = f"""
import glob, hashlib, os, tempfile
from pathlib import Path
import perchpose.io.mavlink.target_relative as tr
digest = hashlib.sha256(tr.DIALECT_XML.read_bytes()).hexdigest()[:12]
folder = Path(tempfile.gettempdir()) / f"perchpose-mavlink-{{digest}}-{{os.getuid()}}"
folder.mkdir(parents=True, exist_ok=True)
(folder / "perchpose_targets.py").write_text("open({str(planted)!r}, 'w').write('x')")
before = set(glob.glob(os.path.join(tempfile.gettempdir(), "perchpose-mavlink-*")))
module = tr.dialect()
after = set(glob.glob(os.path.join(tempfile.gettempdir(), "perchpose-mavlink-*")))
print(module.MAVLINK_MSG_ID_TARGET_RELATIVE, sorted(after - before))
"""
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    out = subprocess.run(
        [sys.executable, "-c", code], check=False, capture_output=True, text=True, env=env
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["511", "[]"]
    assert not planted.exists()
