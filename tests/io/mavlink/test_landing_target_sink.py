"""LANDING_TARGET over a real pymavlink UDP endpoint on the loopback interface."""

import math
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from perchpose.cli import main
from perchpose.control import downward_T_body_camera
from perchpose.errors import LinkError
from perchpose.io.mavlink import link as link_module
from perchpose.io.mavlink.landing_target_sink import LandingTargetSink, mavutil_module
from perchpose.io.sinks import read_track_csv
from perchpose.values import Estimate

DOWN = downward_T_body_camera()  # ArduPilot takes LANDING_TARGET only from a camera looking down


class Receiver:
    """A vehicle-side endpoint (UDP, or a TCP server with ``scheme="tcpin"``): collects what
    arrives, optionally streams its own state (with its heartbeat, as an autopilot does)."""

    def __init__(
        self,
        port: int,
        attitude: tuple[float, float, float] | None = None,
        p_ned_m: tuple[float, float, float] | None = None,
        scheme: str = "udpin",
        clock_offset_ns: int | None = None,
    ) -> None:
        self.conn = mavutil_module().mavlink_connection(f"{scheme}:127.0.0.1:{port}")
        self.messages: list[Any] = []
        # an autopilot's own clock (time since its boot): answers TIMESYNC, asks once itself
        self.clock_offset_ns = clock_offset_ns
        self.asked_ns: int | None = None
        self.attitude = attitude
        self.p_ned_m = p_ned_m
        self._stop = threading.Event()
        self._last_heard_s = time.monotonic()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.05)
            if msg is not None and msg.get_type() != "BAD_DATA":
                self._last_heard_s = time.monotonic()
                self.messages.append(msg)
                if msg.get_type() == "TIMESYNC" and self.clock_offset_ns is not None:
                    self._timesync(msg)
            if self.messages:
                self.conn.mav.heartbeat_send(2, 3, 129, 4, 4)  # an armed ArduCopter
            if self.messages and self.attitude is not None:
                roll, pitch, yaw = self.attitude
                boot_ms = int(time.monotonic() * 1000) & 0xFFFFFFFF  # its clock since boot
                self.conn.mav.attitude_send(boot_ms, roll, pitch, yaw, 0.0, 0.0, 0.0)
                if self.p_ned_m is not None:
                    self.conn.mav.local_position_ned_send(boot_ms, *self.p_ned_m, 0.0, 0.0, 0.0)

    def _timesync(self, msg: Any) -> None:
        assert self.clock_offset_ns is not None
        now = time.monotonic_ns() + self.clock_offset_ns
        if msg.tc1 == 0:
            self.conn.mav.timesync_send(now, msg.ts1)
            if self.asked_ns is None:  # and ask the companion once
                self.asked_ns = now
                self.conn.mav.timesync_send(0, now)

    def of_type(self, name: str) -> list[Any]:
        return [m for m in self.messages if m.get_type() == name]

    def stop(self) -> None:
        # the last datagrams: read until 0.3 s pass without one (a loaded machine's thread
        # may still be behind the sender), 10 s at most
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and time.monotonic() - self._last_heard_s < 0.3:
            time.sleep(0.05)
        self._stop.set()
        self._thread.join()
        self.conn.close()


def frd_from_camera(x_cm: float, y_cm: float, z_cm: float) -> np.ndarray:
    """The downward camera's point in body FRD: image right is the body's right, image down
    its back, the optical axis its down; the camera 15 mm ahead of and 12 mm below the centre."""
    x, y, z = (v / 100.0 for v in (x_cm, y_cm, z_cm))
    return np.array([-y + 0.015, x, z + 0.012])


def test_track_sends_one_landing_target_per_valid_row(
    approach_fpv_dir: Path,
    tmp_path: Path,
    udp_port: int,
    track_argv: Callable[..., list[str]],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # a file is read faster than a camera delivers: on a loaded machine the link's thread can
    # fall more than its queue (8) behind and drop the oldest, which close() then reports
    monkeypatch.setattr(link_module, "QUEUE_LENGTH", 1000)
    receiver = Receiver(udp_port)
    out = tmp_path / "poses.csv"
    try:
        code = main(
            track_argv(
                approach_fpv_dir,
                out,
                "--quiet",
                "--mavlink",
                f"udpout:127.0.0.1:{udp_port}",
                "--mount",
                "down",
            )
        )
    finally:
        receiver.stop()
    assert code == 0
    rows = [r for r in read_track_csv(out) if r["valid"] == "1"]
    assert 0 < len(rows) < len(read_track_csv(out))  # the dropout leaves invalid rows
    sent = receiver.of_type("LANDING_TARGET")
    assert len(sent) == len(rows)
    for row, msg in zip(rows, sent, strict=True):
        assert msg.time_usec == round(float(row["t_s"]) * 1e6)
        assert msg.frame == 12  # MAV_FRAME_BODY_FRD
        assert msg.type == 2  # LANDING_TARGET_TYPE_VISION_FIDUCIAL
        assert msg.position_valid == 1
        x, y, z = (float(row[k]) for k in ("x_cm", "y_cm", "z_cm"))
        assert [msg.x, msg.y, msg.z] == pytest.approx(frd_from_camera(x, y, z), abs=1e-3)
        assert msg.distance == pytest.approx(math.hypot(x, y, z) / 100.0, abs=1e-3)
        assert msg.distance > 0
        assert msg.z > 0  # the line of sight points down, along ArduCopter's descent
        assert msg.angle_x == pytest.approx(math.atan2(x, z), abs=1e-4)
        assert msg.angle_y == pytest.approx(math.atan2(y, z), abs=1e-4)
        # the target's x axis, at yaw psi in the image, points to (-sin psi, cos psi) in FRD
        yaw = math.radians(float(row["yaw_deg"]))
        heading = math.atan2(math.cos(yaw), -math.sin(yaw))
        q = np.array(msg.q)
        assert abs(float(q @ [math.cos(heading / 2), 0, 0, math.sin(heading / 2)])) == (
            pytest.approx(1.0, abs=1e-5)
        )
    beats = receiver.of_type("HEARTBEAT")
    assert beats
    assert beats[0].type == 18  # MAV_TYPE_ONBOARD_CONTROLLER
    assert beats[0].get_srcComponent() == 191  # MAV_COMP_ID_ONBOARD_COMPUTER


def estimate_at(t_s: float, xyz_cm: tuple[float, float, float], yaw_deg: float) -> Estimate:
    x, y, z = (v / 100.0 for v in xyz_cm)
    return Estimate.of_pose(t_s, (x, y, z), math.radians(yaw_deg), stage=1)


def test_local_ned_uses_the_vehicles_attitude_and_position(udp_port: int) -> None:
    roll, pitch, yaw = 0.1, -0.05, 1.2
    p_vehicle = (3.0, -2.0, -1.5)
    receiver = Receiver(udp_port, attitude=(roll, pitch, yaw), p_ned_m=p_vehicle)
    reports: list[str] = []
    sink = LandingTargetSink(
        f"udpout:127.0.0.1:{udp_port}", frame="local_ned", T_body_camera=DOWN, report=reports.append
    )
    try:
        deadline = time.monotonic() + 5.0
        while sink.vehicle.p_ned_m is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert sink.vehicle.R_ned_frd is not None
        assert sink.send(estimate_at(2.5, (4.0, -3.0, 80.0), 30.0))
    finally:
        sink.close()
        receiver.stop()
    (msg,) = receiver.of_type("LANDING_TARGET")
    R_ned_frd = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    expected = R_ned_frd @ frd_from_camera(4.0, -3.0, 80.0) + np.array(p_vehicle)
    assert msg.frame == 1  # MAV_FRAME_LOCAL_NED
    assert [msg.x, msg.y, msg.z] == pytest.approx(expected, abs=1e-4)
    assert msg.time_usec == 2_500_000
    assert not reports


def test_time_usec_is_the_grab_on_the_autopilots_clock(udp_port: int) -> None:
    offset_ns = 7_000_000_000_000 - time.monotonic_ns()  # the vehicle booted 7000 s ago
    receiver = Receiver(udp_port, clock_offset_ns=offset_ns)
    sink = LandingTargetSink(f"udpout:127.0.0.1:{udp_port}", T_body_camera=DOWN)
    try:
        deadline = time.monotonic() + 5.0
        # synchronised, and the vehicle's own request answered
        while (
            sink.timesync.offset_ns is None or not sink.timesync.answered
        ) and time.monotonic() < deadline:
            time.sleep(0.02)
        grabbed = time.monotonic() - 0.04  # its frame was grabbed 40 ms ago
        estimate = replace(estimate_at(0.5, (1.0, 2.0, 60.0), 0.0), grabbed_s=grabbed)
        assert sink.send(estimate)
        assert sink.send(estimate_at(0.6, (1.0, 2.0, 60.0), 0.0))  # no grab time known
    finally:
        sink.close()
        receiver.stop()
    # an answer read late (the link's thread polls) or sent late (the vehicle's) biases the
    # offset by half the difference, never more than half the round trip it came from
    rtt_ns = sink.timesync.rtt_ns
    assert rtt_ns is not None
    assert rtt_ns < 50_000_000
    bound_ns = rtt_ns / 2 + 100_000
    assert sink.timesync.offset_ns == pytest.approx(offset_ns, abs=bound_ns)
    with_grab, without = receiver.of_type("LANDING_TARGET")
    expected_usec = (grabbed * 1e9 + offset_ns) / 1000
    assert with_grab.time_usec == pytest.approx(expected_usec, abs=bound_ns / 1000 + 1)
    assert without.time_usec == 600_000  # the frame's own time, as before TIMESYNC
    # the vehicle's own request was answered with the companion's clock, its ts1 echoed
    answers = [m for m in receiver.of_type("TIMESYNC") if m.tc1 != 0]
    assert [m.ts1 for m in answers] == [receiver.asked_ns]
    assert sink.timesync.answered == 1


def test_local_ned_waits_for_attitude(udp_port: int) -> None:
    reports: list[str] = []
    sink = LandingTargetSink(
        f"udpout:127.0.0.1:{udp_port}", frame="local_ned", report=reports.append
    )
    try:
        assert not sink.send(estimate_at(0.0, (0.0, 0.0, 50.0), 0.0))
        assert not sink.send(estimate_at(0.1, (0.0, 0.0, 50.0), 0.0))
    finally:
        sink.close()
    assert len(reports) == 1
    assert "ATTITUDE" in reports[0]


def test_stale_and_non_finite_estimates_are_never_sent(udp_port: int) -> None:
    """Only fresh, finite poses leave: a coasted estimate older than max_age_s is refused
    (reported once); a NaN attitude from the vehicle is dropped by the link (reported once),
    so local_ned has none to turn by and holds its estimates back; a fresh one still goes out
    in body_frd."""
    receiver = Receiver(udp_port, attitude=(math.nan, 0.0, 0.0))
    reports: list[str] = []
    body = LandingTargetSink(
        f"udpout:127.0.0.1:{udp_port}", T_body_camera=DOWN, max_age_s=0.3, report=reports.append
    )
    ned = LandingTargetSink(
        f"udpout:127.0.0.1:{udp_port}", frame="local_ned", report=reports.append
    )
    try:
        fresh = estimate_at(1.0, (2.0, 1.0, 50.0), 10.0)
        old = Estimate.of_pose(1.1, fresh.t_camera_target_m, fresh.yaw_rad, age_s=0.5)
        assert not body.send(old)
        assert body.send(fresh)
        assert body.refused == 1
        deadline = time.monotonic() + 5.0
        while ned.vehicle.rejected == 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not ned.send(fresh)  # the attitude the vehicle sent is NaN
        assert ned.vehicle.R_ned_frd is None
    finally:
        body.close()
        ned.close()
        receiver.stop()
    (msg,) = receiver.of_type("LANDING_TARGET")
    assert msg.time_usec == 1_000_000
    assert all(math.isfinite(v) for v in (msg.x, msg.y, msg.z, msg.angle_x, msg.distance))
    assert "0.50 s old" in reports[0]
    # each link says it once (the vehicle answers whichever link spoke last, so the body_frd
    # sink's link may or may not have had a NaN attitude too)
    nan = [r for r in reports if "ATTITUDE dropped: non-finite" in r]
    assert 1 <= len(nan) <= 2
    assert all("(reported once; the link goes on)" in r for r in nan)
    held = [r for r in reports if "no ATTITUDE from the vehicle yet; local_ned" in r]
    assert len(held) == 1
    assert len(reports) == 2 + len(nan)


def test_a_link_that_cannot_open_is_reported_once_and_tracking_goes_on() -> None:
    reports: list[str] = []
    sink = LandingTargetSink(
        "/dev/perchpose-no-such-port,57600",
        T_body_camera=DOWN,
        retry_period_s=0.05,
        report=reports.append,
    )
    try:
        accepted = []
        for i in range(5):
            accepted.append(sink.send(estimate_at(i / 30, (0.0, 0.0, 50.0), 0.0)))
            time.sleep(0.06)  # retries happen meanwhile
    finally:
        sink.close()
    # the first may be queued while the link's thread first tries to open it
    assert not any(accepted[1:])
    assert sink.sent == 0
    assert sink.dropped == 5
    assert len(reports) == 2
    assert "/dev/perchpose-no-such-port" in reports[0]
    assert "5 of 5 messages dropped unsent" in reports[1]


@pytest.mark.parametrize("url", ["udpout:127.0.0.1", "udpout:host:99999", "nonsense", ""])
def test_bad_urls_are_refused(url: str) -> None:
    with pytest.raises(LinkError, match="MAVLink URL"):
        LandingTargetSink(url, T_body_camera=DOWN)


def test_arducopter_would_drop_a_target_above_so_it_is_refused() -> None:
    """ArduCopter takes a LANDING_TARGET only along its descent: body_frd from the default
    upward camera (or one looking sideways) is refused with what to use instead; PX4's
    local_ned is not refused, nor body_frd from a camera looking down."""
    from perchpose.control import default_T_body_camera
    from perchpose.geometry import make_transform, rot_x

    with pytest.raises(LinkError, match=r"looking up.*--mount down.*--crazyflie"):
        LandingTargetSink("udpout:127.0.0.1:14550")
    sideways = make_transform(rot_x(math.pi / 2), np.zeros(3))
    with pytest.raises(LinkError, match="looking sideways"):
        LandingTargetSink("udpout:127.0.0.1:14550", T_body_camera=sideways)
    for sink in (
        LandingTargetSink("udpout:127.0.0.1:14550", frame="local_ned"),
        LandingTargetSink(
            "udpout:127.0.0.1:14550", frame="local_ned", T_body_camera=default_T_body_camera()
        ),
        LandingTargetSink("udpout:127.0.0.1:14550", T_body_camera=DOWN),
    ):
        sink.close()


def test_cli_refuses_landing_target_to_ardupilot_from_an_upward_camera(
    approach_fpv_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    udp_port: int,
    track_argv: Callable[..., list[str]],
) -> None:
    out = tmp_path / "p.csv"
    code = main(track_argv(approach_fpv_dir, out, "--mavlink", f"udpout:127.0.0.1:{udp_port}"))
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "--mount down" in err[0]
    assert not out.exists()  # refused before the first frame


def test_cli_reports_a_bad_url(
    approach_fpv_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    track_argv: Callable[..., list[str]],
) -> None:
    code = main(
        track_argv(
            approach_fpv_dir,
            tmp_path / "p.csv",
            "--mavlink",
            "udpout:localhost",
            camera="preset:fpv",
        )
    )
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "udpout:localhost" in err[0]


def _send_until(sink: LandingTargetSink, vehicle: Receiver, count: int, t0: float) -> None:
    deadline = time.monotonic() + 10.0
    k = 0
    while len(vehicle.of_type("LANDING_TARGET")) < count and time.monotonic() < deadline:
        sink.send(estimate_at(t0 + k / 30, (0.0, 0.0, 50.0), 0.0))
        k += 1
        time.sleep(1 / 30)


def test_tcp_link_survives_the_vehicle_restarting(
    capfd: pytest.CaptureFixture[str], tcp_port: int
) -> None:
    """Peer down at the start, up, closed, up again: reported once per outage, reconnected
    each time, and nothing printed to stdout."""
    reports: list[str] = []
    sink = LandingTargetSink(
        f"tcp:127.0.0.1:{tcp_port}", T_body_camera=DOWN, retry_period_s=0.1, report=reports.append
    )
    vehicle = None
    try:
        for _ in range(5):  # nobody listens yet: dropped, never blocking the caller
            sink.send(estimate_at(0.0, (0.0, 0.0, 50.0), 0.0))
            time.sleep(0.05)
        assert not sink.connected
        for t0 in (1.0, 3.0):  # the vehicle starts, then restarts
            if vehicle is not None:
                vehicle.stop()  # the vehicle closes the connection
                deadline = time.monotonic() + 5.0
                while sink.connected and time.monotonic() < deadline:
                    sink.send(estimate_at(2.0, (0.0, 0.0, 50.0), 0.0))
                    time.sleep(0.05)
                assert not sink.connected
            vehicle = Receiver(tcp_port, scheme="tcpin")
            _send_until(sink, vehicle, 3, t0)
            received = vehicle.of_type("LANDING_TARGET")
            assert len(received) >= 3
            assert received[-1].time_usec >= t0 * 1e6
    finally:
        sink.close()
        if vehicle is not None:
            vehicle.stop()
    out = capfd.readouterr().out
    assert out == ""
    downs = [r for r in reports if "retrying" in r]
    ups = [r for r in reports if "link up again" in r]
    assert len(downs) == 2
    assert len(ups) == 2


def test_distance_sensor_gives_the_range_along_the_bodys_vertical() -> None:
    """The downward camera 12 mm under the centre sees the target 80 cm along its axis: a
    rangefinder looking down (PITCH_270) reads 81 cm, with the depth variance in cm^2; the
    upward camera's reading looks up (PITCH_90); nothing for a sideways camera."""
    from perchpose.control import default_T_body_camera
    from perchpose.geometry import make_transform, rot_x
    from perchpose.io.mavlink.landing_target import distance_reading

    estimate = replace(
        estimate_at(0.5, (3.0, -2.0, 80.0), 0.0),
        covariance_flat=tuple(float(v) for v in np.diag([1e-6, 1e-6, 4e-4, 0, 0, 0]).ravel()),
    )
    down = distance_reading(estimate, DOWN, 500)
    assert down is not None
    assert (down.current_cm, down.covariance_cm2, down.orientation) == (81, 4, 25)
    up = distance_reading(estimate, default_T_body_camera(), 500)
    assert up is not None
    assert (up.current_cm, up.orientation) == (81, 24)
    sideways = make_transform(rot_x(math.pi / 2), np.zeros(3))
    assert distance_reading(estimate, sideways, 500) is None
    assert distance_reading(estimate, DOWN, 50) is None  # beyond the sensor's range
    no_covariance = distance_reading(estimate_at(0.5, (0.0, 0.0, 80.0), 0.0), DOWN, 500)
    assert no_covariance is not None
    assert no_covariance.covariance_cm2 == 255  # unknown


def test_distance_sensor_goes_out_with_each_landing_target(udp_port: int) -> None:
    receiver = Receiver(udp_port)
    sink = LandingTargetSink(
        f"udpout:127.0.0.1:{udp_port}", T_body_camera=DOWN, distance_sensor=True
    )
    try:
        for k in range(3):
            assert sink.send(estimate_at(k / 30, (0.0, 0.0, 60.0 + k), 0.0))
        deadline = time.monotonic() + 5.0
        while len(receiver.of_type("DISTANCE_SENSOR")) < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        sink.close()
        receiver.stop()
    readings = receiver.of_type("DISTANCE_SENSOR")
    assert [m.current_distance for m in readings] == [61, 62, 63]
    assert all(m.orientation == 25 and m.min_distance == 5 for m in readings)
    assert all(m.max_distance == 500 and m.covariance == 255 for m in readings)


def test_no_packet_ends_the_link(udp_port: int) -> None:
    """A TIMESYNC answer with a negative time (a clock 'before boot'), a message whose field
    cannot be packed, an estimate before time zero: each is dropped or ignored and said once,
    and LANDING_TARGET and HEARTBEAT go on."""
    negative_clock_ns = -time.monotonic_ns() - 100_000_000_000  # the vehicle answers tc1 < 0
    receiver = Receiver(udp_port, clock_offset_ns=negative_clock_ns)
    reports: list[str] = []
    sink = LandingTargetSink(
        f"udpout:127.0.0.1:{udp_port}",
        T_body_camera=DOWN,
        timesync_period_s=0.1,
        report=reports.append,
    )
    try:
        wait_until(lambda: len(receiver.of_type("TIMESYNC")) >= 3)
        time.sleep(0.1)  # the answers are in
        grabbed = replace(estimate_at(0.5, (1.0, 2.0, 60.0), 0.0), grabbed_s=time.monotonic())
        assert sink.send(grabbed)
        unpackable = lambda mav: mav.landing_target_send(-1, 0, 12, 0, 0, 0, 0, 0, 0)  # noqa: E731
        assert sink.link.post(unpackable, "LANDING_TARGET")
        assert sink.link.post(unpackable, "LANDING_TARGET")
        assert not sink.send(estimate_at(-1.0, (1.0, 2.0, 60.0), 0.0))
        for i in range(5):
            assert sink.send(estimate_at(1.0 + i / 30, (1.0, 2.0, 60.0), 0.0))
        wait_until(lambda: len(receiver.of_type("LANDING_TARGET")) >= 6)
        beats = len(receiver.of_type("HEARTBEAT"))
        time.sleep(1.2)
        assert len(receiver.of_type("HEARTBEAT")) > beats  # the link's thread lives
        assert sink.connected
    finally:
        sink.close()
        receiver.stop()
    targets = receiver.of_type("LANDING_TARGET")
    assert len(targets) == 6
    assert targets[0].time_usec == 500_000  # no usable clock offset: the frame's time
    assert sink.timesync.offset_ns is None
    assert sink.timesync.ignored >= 1
    assert sink.link.faults == 2
    assert sink.refused == 1
    unsent = [r for r in reports if "one LANDING_TARGET could not be sent" in r]
    assert len(unsent) == 1
    assert any("before time zero; not sent" in r for r in reports)


def wait_until(condition: Callable[[], bool], seconds: float = 5.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert condition()


def test_the_link_uses_only_its_vehicles_messages() -> None:
    """Decoded by pymavlink's own parser: the first autopilot's HEARTBEAT locks the link on to
    its system and component; another autopilot is a stranger, a ground station or another
    component of the vehicle is neither, and nothing but the vehicle's samples is kept."""
    from perchpose.io.mavlink.link import VehicleState

    mavlink = mavutil_module().mavlink

    def received(system: int, component: int, build: Callable[[Any], Any]) -> Any:
        sender = mavlink.MAVLink(None, srcSystem=system, srcComponent=component)
        return mavlink.MAVLink(None).decode(bytearray(build(sender).pack(sender)))

    def beat(mav: Any) -> Any:
        return mav.heartbeat_encode(2, 3, 129, 4, 4)

    def gcs(mav: Any) -> Any:
        return mav.heartbeat_encode(6, 8, 0, 0, 4)

    def attitude(mav: Any) -> Any:
        return mav.attitude_encode(1000, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0)

    def nan_attitude(mav: Any) -> Any:
        return mav.attitude_encode(1020, math.nan, 0.0, 0.0, 0.0, 0.0, 0.0)

    state = VehicleState()
    assert state.source(received(3, 1, attitude)) == "other"  # not locked yet
    assert state.source(received(255, 190, gcs)) == "other"
    assert state.source(received(3, 1, beat)) == "vehicle"
    assert (state.system_id, state.component_id) == (3, 1)
    assert state.source(received(4, 1, beat)) == "stranger"
    assert state.source(received(4, 1, attitude)) == "other"
    assert state.source(received(3, 154, attitude)) == "other"  # a gimbal of the vehicle
    own = received(3, 1, attitude)
    assert state.source(own) == "vehicle"
    assert state.heard(own, 1.0)
    assert state.heard(received(3, 1, nan_attitude), 2.0) is False
    assert state.rejected == 1
    assert state.attitude_t_s == 1.0  # the last good one stays, and ages
    assert state.attitude_age_s(1.5) == pytest.approx(0.5)
    chosen = VehicleState(target_system=4)
    assert chosen.source(received(3, 1, beat)) == "stranger"
    assert chosen.source(received(4, 1, beat)) == "vehicle"


def test_a_live_frame_that_waited_is_never_sent(udp_port: int) -> None:
    """A live frame measured 0.6 s after its grab (the estimator stalled on a compile, say)
    is as old as that when it would reach the vehicle: refused, though its own measurement is
    fresh (``age_s`` 0); one grabbed 0.1 s ago goes out."""
    receiver = Receiver(udp_port)
    reports: list[str] = []
    sink = LandingTargetSink(
        f"udpout:127.0.0.1:{udp_port}", T_body_camera=DOWN, report=reports.append
    )
    try:
        fresh = estimate_at(1.0, (2.0, 1.0, 50.0), 10.0)
        waited = replace(fresh, grabbed_s=time.monotonic() - 0.6)
        assert waited.age_s == 0.0
        assert not sink.send(waited)
        late = replace(fresh, grabbed_s=time.monotonic() - 0.2, camera_latency_s=0.4)
        assert not sink.send(late)  # captured 0.6 s ago, though grabbed 0.2 s ago
        assert sink.send(replace(fresh, t_s=1.1, grabbed_s=time.monotonic() - 0.1))
    finally:
        sink.close()
        receiver.stop()
    assert sink.refused == 2
    assert len(receiver.of_type("LANDING_TARGET")) == 1
    assert "s old (limit 0.5 s); not sent" in reports[0]
