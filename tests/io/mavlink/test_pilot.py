"""Perching with an autopilot, checked at the autopilot's rules against a pymavlink endpoint on
loopback that plays the vehicle: HEARTBEAT with its mode, ATTITUDE, LOCAL_POSITION_NED and
HIGHRES_IMU at 50 Hz, and what it receives kept with the mode it was in."""

import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from perchpose.cli import main
from perchpose.control import ControllerSettings, PerchingController, PilotSettings
from perchpose.io.mavlink import link as mavlink_link
from perchpose.io.mavlink.landing_target_sink import mavutil_module
from perchpose.io.mavlink.link import MavlinkLink
from perchpose.io.mavlink.pilot import MavlinkPilot, SetpointCommander
from perchpose.values import Estimate

ARDUPILOT, PX4 = 3, 12
LOITER, GUIDED = 5, 4  # ArduCopter custom modes
POSCTL, OFFBOARD = 3 << 16, 6 << 16  # PX4 main modes in custom_mode's third byte
ARMED = 128 | 1  # MAV_MODE_FLAG_SAFETY_ARMED | MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


class Vehicle:
    """An autopilot on ``udpin``: level, still, 1 m up, in ``mode``; heartbeats at 10 Hz
    (and at once on a mode change) until ``silent``; ATTITUDE, LOCAL_POSITION_NED and
    HIGHRES_IMU (its accelerometer: ``push_frd_mps2`` along the body's x and y, -g along z) at
    50 Hz while ``streams`` names them, each sample through ``sample`` (to spoil one). ``stranger``:
    a second autopilot on the same link (system 2, disarmed in LOITER, rolled 30 deg) sends
    its heartbeats and attitude too."""

    def __init__(
        self, port: int, autopilot: int, mode: int, system: int = 7, stranger: bool = False
    ) -> None:
        self.conn = mavutil_module().mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=system, source_component=1
        )
        self.system = system
        self.autopilot = autopilot
        self.mode = mode
        self.armed = True
        self.silent = False
        self.stranger = stranger
        self.streams = {"ATTITUDE", "LOCAL_POSITION_NED", "HIGHRES_IMU"}
        self.push_frd_mps2 = (0.0, 0.0)
        self.height_m = 1.0
        self.flies = False  # its height follows the vertical speed it is sent (floor at 0)
        self._stated_s: float | None = None  # when it last sent its state
        self.vz_ned_mps = 0.0
        self.disarmed_at_m: float | None = None
        self.boot_offset_ms = 0  # a reboot: its clock since boot starts again
        self.floor_m = 0.0  # what it lands on, above its local origin (a roof: higher)
        self.land_detector = False  # sends EXTENDED_SYS_STATE with its landed state
        self.spoil: set[str] = set()  # the next sample of these kinds carries a NaN
        self.received: list[tuple[int, Any]] = []  # (the mode it arrived in, message)
        self._stop = threading.Event()
        self._last_heard_s = time.monotonic()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def set_mode(self, mode: int) -> None:
        self.mode = mode
        self._beat()

    def _beat(self) -> None:
        if not self.silent and self.received:
            base_mode = ARMED if self.armed else 1
            self.conn.mav.heartbeat_send(2, self.autopilot, base_mode, self.mode, 4)

    def _run(self) -> None:
        next_beat = next_state = 0.0
        while not self._stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.005)
            if msg is not None and msg.get_type() != "BAD_DATA":
                self._last_heard_s = time.monotonic()
                self.received.append((self.mode, msg))
                self._obey(msg)
            now = time.monotonic()
            if now >= next_beat:
                next_beat = now + 0.1
                self._beat()
            if self.received and now >= next_state:
                next_state = now + 0.02
                self._state(now)

    def _obey(self, msg: Any) -> None:
        """Fly a velocity setpoint (when ``flies``), disarm or change mode as told."""
        kind = msg.get_type()
        if kind == "SET_POSITION_TARGET_LOCAL_NED" and self.armed:
            self.vz_ned_mps = msg.vz
        elif kind == "COMMAND_LONG" and msg.command == 400 and msg.param1 == 0:
            self.armed = False
            self.vz_ned_mps = 0.0
            self.disarmed_at_m = self.height_m
        elif kind == "COMMAND_LONG" and msg.command == 176:
            self.set_mode(int(msg.param2))

    def _state(self, now_s: float) -> None:
        nan = float("nan")
        # it moves in real time, however late this thread runs on a busy machine
        dt_s = 0.02 if self._stated_s is None else now_s - self._stated_s
        self._stated_s = now_s
        if self.flies:
            self.height_m = max(self.floor_m, self.height_m - self.vz_ned_mps * dt_s)
        resting = self.height_m <= self.floor_m
        vz = self.vz_ned_mps if self.flies and not resting else 0.0
        if self.land_detector:
            self.conn.mav.extended_sys_state_send(0, 1 if resting else 2)
        boot_ms = int(time.monotonic() * 1000 - self.boot_offset_ms) & 0xFFFFFFFF
        if "ATTITUDE" in self.streams:
            roll = nan if "ATTITUDE" in self.spoil else 0.0
            self.spoil.discard("ATTITUDE")
            self.conn.mav.attitude_send(boot_ms, roll, 0.0, 0.0, 0.0, 0.0, 0.0)
        if "LOCAL_POSITION_NED" in self.streams:
            x = nan if "LOCAL_POSITION_NED" in self.spoil else 0.0
            self.spoil.discard("LOCAL_POSITION_NED")
            self.conn.mav.local_position_ned_send(boot_ms, x, 0.0, -self.height_m, 0.0, 0.0, vz)
        if "HIGHRES_IMU" in self.streams:
            ax, ay = self.push_frd_mps2
            zero = (0.0,) * 10
            self.conn.mav.highres_imu_send(boot_ms * 1000, ax, ay, -9.81, *zero, 7)
        if self.stranger:  # the same socket, another system id
            self.conn.mav.srcSystem = 2
            self.conn.mav.heartbeat_send(2, self.autopilot, 1, LOITER, 4)
            self.conn.mav.attitude_send(boot_ms, math.radians(30.0), 0.0, 0.0, 0.0, 0.0, 0.0)
            self.conn.mav.local_position_ned_send(boot_ms, 5.0, 5.0, -3.0, 1.0, 0.0, 0.0)
            self.conn.mav.srcSystem = self.system

    def setpoints(self) -> list[tuple[int, Any]]:
        return [
            (m, msg)
            for m, msg in self.received
            if msg.get_type() == "SET_POSITION_TARGET_LOCAL_NED"
        ]

    def stop(self) -> None:
        # the last datagrams: read until 0.3 s pass without one (a loaded machine's thread
        # may still be behind the sender; a fixed 0.2 s once missed the final hover), 10 s at
        # most, as the landing-target sink's vehicle does
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and time.monotonic() - self._last_heard_s < 0.3:
            time.sleep(0.05)
        self._stop.set()
        self._thread.join()
        self.conn.close()


def fly(pilot: MavlinkPilot, seconds: float, xyz_m: tuple[float, float, float], t0: float) -> int:
    """Hand the pilot a frame every 1/30 s for ``seconds``; the number of frames."""
    frames = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pilot(Estimate.of_pose(time.monotonic() - t0, xyz_m, 0.0, stage=1), time.monotonic() - t0)
        frames += 1
        time.sleep(1 / 30)
    return frames


def wait_for(condition: Any, seconds: float = 5.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert condition()


def test_ardupilot_gets_setpoints_only_in_guided_and_the_pilot_stops_when_it_leaves(
    udp_port: int,
) -> None:
    vehicle = Vehicle(udp_port, ARDUPILOT, LOITER)
    reports: list[str] = []
    pilot = MavlinkPilot(f"udpout:127.0.0.1:{udp_port}", report=reports.append)
    ahead = (0.10, 0.0, 0.6)  # the upward camera's x is the body's front: the target is ahead
    t0 = time.monotonic()
    try:
        wait_for(lambda: pilot.vehicle.autopilot == ARDUPILOT and pilot.odometry() is not None)
        fly(pilot, 0.5, ahead, t0)
        assert pilot.pilot.state == "waiting"
        vehicle.set_mode(GUIDED)
        wait_for(pilot.engaged)
        frames = fly(pilot, 1.5, ahead, t0)
        assert pilot.pilot.state == "perching"
        vehicle.set_mode(LOITER)
        wait_for(lambda: pilot.pilot.state == "released")
        time.sleep(0.1)  # what was on the way when the heartbeat came
        before = len(vehicle.setpoints())
        fly(pilot, 0.5, ahead, t0)
        time.sleep(0.2)
        assert len(vehicle.setpoints()) == before  # nothing after the release
    finally:
        pilot.close()
        vehicle.stop()
    sent = vehicle.setpoints()
    assert len(sent) >= frames  # one per frame at least, and more on odometry between them
    assert all(msg.coordinate_frame == 1 and msg.type_mask == 1479 for _, msg in sent)
    assert all(msg.target_system == 7 for _, msg in sent)
    guided = [msg for mode, msg in sent if mode == GUIDED]
    assert len(guided) >= len(sent) - 5  # only the last few can cross the switch to LOITER
    vx = np.array([msg.vx for msg in guided])
    vy = np.array([msg.vy for msg in guided])
    assert np.mean(vx) > 0.02  # north, towards the target ahead
    assert np.mean(np.abs(vy)) < 0.2 * np.mean(vx)
    assert any("waiting for the vehicle to be armed in GUIDED" in r for r in reports)
    assert any("left GUIDED" in r for r in reports)
    assert not any("hover setpoint" in r for r in reports)  # already released, not twice
    assert not any("velocity setpoints only" in r for r in reports)  # asked velocities


def test_px4_gets_a_proof_of_life_stream_then_offboard_setpoints_until_its_heartbeat_stops(
    udp_port: int,
) -> None:
    vehicle = Vehicle(udp_port, PX4, POSCTL)
    reports: list[str] = []
    pilot = MavlinkPilot(
        f"udpout:127.0.0.1:{udp_port}", heartbeat_timeout_s=0.5, report=reports.append
    )
    left = (0.0, 0.10, 0.6)  # the camera's y is the body's left
    t0 = time.monotonic()
    try:
        wait_for(lambda: pilot.proof_of_life >= 3)
        # and the vehicle has them, before its mode changes under a datagram still in flight
        wait_for(lambda: sum(mode == POSCTL for mode, _ in vehicle.setpoints()) >= 3)
        assert pilot.pilot.state == "waiting"
        vehicle.set_mode(OFFBOARD)
        wait_for(pilot.engaged)
        fly(pilot, 1.0, left, t0)
        assert pilot.pilot.state == "perching"
        vehicle.silent = True
        wait_for(lambda: pilot.pilot.state == "released")
        time.sleep(0.1)
        before = len(vehicle.setpoints())
        fly(pilot, 0.3, left, t0)
        time.sleep(0.2)
        assert len(vehicle.setpoints()) == before
    finally:
        pilot.close()
        vehicle.stop()
    sent = vehicle.setpoints()
    waiting = [msg for mode, msg in sent if mode == POSCTL]
    assert len(waiting) >= 3
    assert all((msg.vx, msg.vy, msg.vz, msg.yaw_rate) == (0, 0, 0, 0) for msg in waiting)
    offboard = [msg for mode, msg in sent if mode == OFFBOARD]
    vy = np.array([msg.vy for msg in offboard])
    assert np.mean(vy) < -0.02  # west in NED is -y: towards the target on the left
    assert any("no HEARTBEAT" in r for r in reports)


def test_a_vehicle_that_disarms_in_guided_releases_the_pilot(udp_port: int) -> None:
    vehicle = Vehicle(udp_port, ARDUPILOT, GUIDED)
    reports: list[str] = []
    pilot = MavlinkPilot(f"udpout:127.0.0.1:{udp_port}", report=reports.append)
    t0 = time.monotonic()
    try:
        wait_for(pilot.ready)
        fly(pilot, 0.3, (0.0, 0.0, 0.6), t0)
        assert pilot.pilot.state == "perching"
        vehicle.armed = False
        vehicle.set_mode(GUIDED)  # a heartbeat now
        wait_for(lambda: pilot.pilot.state == "released")
    finally:
        pilot.close()
        vehicle.stop()
    assert any("disarmed" in r for r in reports)


def test_setpoints_and_stops_in_the_autopilots_frames(udp_port: int) -> None:
    """World z up to NED (y and z negated, the yaw rate too, in rad/s); a stop on the plate is
    a forced disarm, any other a normal one; nothing at all while not allowed."""
    vehicle = Vehicle(udp_port, ARDUPILOT, GUIDED)
    link = MavlinkLink(f"udpout:127.0.0.1:{udp_port}")
    allowed = [True]
    force = [False]
    commander = SetpointCommander(link, lambda: allowed[0], lambda: force[0])
    try:
        wait_for(lambda: link.vehicle.autopilot == ARDUPILOT)
        commander.send_velocity((0.1, 0.2, 0.3), math.radians(10.0))
        commander.send_stop()
        force[0] = True
        commander.send_stop()
        allowed[0] = False
        commander.send_velocity((0.1, 0.2, 0.3), math.radians(10.0))
        commander.send_stop()
        wait_for(
            lambda: len([m for _, m in vehicle.received if m.get_type() == "COMMAND_LONG"]) >= 2
        )
    finally:
        link.close()
        vehicle.stop()
    (setpoint,) = [msg for _, msg in vehicle.setpoints()]
    assert [setpoint.vx, setpoint.vy, setpoint.vz] == pytest.approx([0.1, -0.2, -0.3])
    assert setpoint.yaw_rate == pytest.approx(-math.radians(10.0))
    commands = [msg for _, msg in vehicle.received if msg.get_type() == "COMMAND_LONG"]
    assert [(c.command, c.param1, c.param2) for c in commands] == [(400, 0, 0), (400, 0, 21196)]
    assert commander.withheld == 2


def test_track_flies_the_autopilot_and_hands_it_back_at_the_end(
    approach_fpv_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    udp_port: int,
    track_argv: Callable[..., list[str]],
) -> None:
    vehicle = Vehicle(udp_port, ARDUPILOT, GUIDED)
    try:
        code = main(
            track_argv(
                approach_fpv_dir,
                tmp_path / "p.csv",
                "--quiet",
                "--mavlink",
                f"udpout:127.0.0.1:{udp_port}",
                "--mavlink-pilot",
                "--realtime",
            )
        )
    finally:
        vehicle.stop()
    assert code == 0
    err = capsys.readouterr().err
    kinds = {msg.get_type() for _, msg in vehicle.received}
    assert "LANDING_TARGET" not in kinds
    assert "waiting -> perching" in err  # track waited for the vehicle before the first frame
    assert "tracking ended: a hover setpoint" in err
    assert "MAVLink pilot: took over at t = " in err
    sent = vehicle.setpoints()
    assert any(msg.vz < 0 for _, msg in sent)  # it climbed (NED z down) towards the target
    last = sent[-1][1]
    assert (last.vx, last.vy, last.vz) == (0, 0, 0)


def test_mavlink_pilot_needs_a_link(
    approach_fpv_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    track_argv: Callable[..., list[str]],
) -> None:
    code = main(
        track_argv(approach_fpv_dir, tmp_path / "p.csv", "--mavlink-pilot", camera="preset:fpv")
    )
    assert code == 2
    assert "--mavlink-pilot needs --mavlink" in capsys.readouterr().err


@contextmanager
def guided(
    udp_port: int, stranger: bool = False, **pilot_options: Any
) -> Iterator[tuple[Vehicle, MavlinkPilot, list[str]]]:
    """An ArduPilot vehicle armed in GUIDED and the pilot on its link, ready; both closed at
    the end. Yields the vehicle, the pilot and the pilot's reports."""
    vehicle = Vehicle(udp_port, ARDUPILOT, GUIDED, stranger=stranger)
    reports: list[str] = []
    pilot = MavlinkPilot(f"udpout:127.0.0.1:{udp_port}", report=reports.append, **pilot_options)
    try:
        wait_for(pilot.ready)
        yield vehicle, pilot, reports
    finally:
        pilot.close()
        vehicle.stop()


def steering(sent: list[tuple[int, Any]]) -> list[Any]:
    return [msg for _, msg in sent if (msg.vx, msg.vy, msg.vz) != (0, 0, 0)]


def test_the_pilot_flies_its_own_system_and_ignores_a_stranger(udp_port: int) -> None:
    """A second autopilot on the link (system 2, disarmed in LOITER, rolled 30 deg, elsewhere)
    neither receives a setpoint nor feeds the pilot's state nor releases it."""
    with guided(udp_port, stranger=True, target_system=7) as (vehicle, pilot, reports):
        fly(pilot, 1.0, (0.10, 0.0, 0.6), time.monotonic())
        assert pilot.pilot.state == "perching"
        np.testing.assert_allclose(pilot.attitude(), np.eye(3), atol=1e-9)
        p_nwu, v_nwu = pilot.odometry() or (None, None)
        np.testing.assert_allclose(p_nwu, [0.0, 0.0, 1.0])
        np.testing.assert_allclose(v_nwu, [0.0, 0.0, 0.0])
    sent = vehicle.setpoints()
    assert len(steering(sent)) > 10
    assert {msg.target_system for _, msg in sent} == {7}
    assert any("ignoring autopilot system 2" in r for r in reports)
    assert not any("disarmed" in r or "left GUIDED" in r for r in reports)
    assert reports[-1].startswith("MAVLink pilot: took over at t = ")
    assert reports[-1].endswith("ended released")  # by the end of tracking, not system 2


def test_no_tick_sends_a_setpoint_after_the_last_hover(udp_port: int) -> None:
    """The link's thread ticks the pilot on every LOCAL_POSITION_NED. One that runs while
    ``close`` sends its hover waits for the release and then sends nothing: the hover is the
    last setpoint the vehicle gets."""
    vehicle = Vehicle(udp_port, ARDUPILOT, GUIDED)
    pilot = MavlinkPilot(f"udpout:127.0.0.1:{udp_port}", report=lambda _line: None)
    try:
        wait_for(pilot.ready)
        fly(pilot, 0.5, (0.10, 0.0, 0.6), time.monotonic())
        assert pilot.pilot.state == "perching"
        hover = pilot.commander.velocity
        ticked = threading.Event()

        def hover_while_the_link_ticks(v_ned: tuple[float, float, float], yaw: float) -> None:
            hover(v_ned, yaw)
            # a tick on another thread, as the link's thread would run one, right after
            tick = threading.Thread(target=lambda: (pilot.pilot.tick_now(), ticked.set()))
            tick.start()
            tick.join(timeout=0.3)  # it cannot run while close holds the pilot

        pilot.commander.velocity = hover_while_the_link_ticks  # type: ignore[method-assign]
        pilot.close()
        assert ticked.wait(2.0)  # it ran once the pilot was released, and sent nothing
    finally:
        vehicle.stop()
    last = vehicle.setpoints()[-1][1]
    assert (last.vx, last.vy, last.vz) == (0, 0, 0)
    assert len(steering(vehicle.setpoints())) > 5


def test_the_first_autopilot_heard_is_the_one_flown(udp_port: int) -> None:
    with guided(udp_port) as (vehicle, pilot, _reports):
        vehicle.stranger = True
        time.sleep(0.3)
        assert pilot.vehicle.system_id == 7
        np.testing.assert_allclose(pilot.attitude(), np.eye(3), atol=1e-9)
        assert pilot.vehicle.armed
        assert pilot.vehicle.custom_mode == GUIDED


def test_one_nan_sample_is_dropped_and_the_pilot_keeps_steering(udp_port: int) -> None:
    with guided(udp_port) as (vehicle, pilot, reports):
        t0 = time.monotonic()
        fly(pilot, 0.5, (0.10, 0.0, 0.6), t0)
        vehicle.spoil = {"ATTITUDE", "LOCAL_POSITION_NED"}
        wait_for(lambda: not vehicle.spoil)
        time.sleep(0.1)
        before = len(vehicle.setpoints())
        fly(pilot, 1.0, (0.10, 0.0, 0.6), t0)
        assert pilot.pilot.state == "perching"
    after = vehicle.setpoints()[before:]
    assert len(after) > 20
    assert len(steering(after)) >= len(after) - 2  # the last: the hover at close
    assert all(math.isfinite(msg.vx) and msg.vx > 0.0 for msg in steering(after))
    assert pilot.vehicle.rejected == 2
    assert any("ATTITUDE dropped: non-finite" in r for r in reports)
    assert pilot.pilot.replaced_setpoints == 0


@pytest.mark.parametrize("stream", ["ATTITUDE", "LOCAL_POSITION_NED"])
def test_a_stream_that_stops_holds_the_vehicle_then_hands_it_back(
    udp_port: int, stream: str
) -> None:
    """A quarter of a second without the stream: hover setpoints (no climb); after a second,
    released to the autopilot, saying why; nothing sent after that."""
    above = (0.0, 0.0, 0.6)
    with guided(udp_port) as (vehicle, pilot, reports):
        t0 = time.monotonic()
        fly(pilot, 0.5, above, t0)
        assert any(msg.vz < -0.05 for _, msg in vehicle.setpoints())  # climbing (NED z down)
        vehicle.streams.discard(stream)
        fly(pilot, 0.35, above, t0)  # past the quarter of a second
        time.sleep(0.05)
        holding = len(vehicle.setpoints())
        end = time.monotonic() + 2.0
        while pilot.pilot.state != "released" and time.monotonic() < end:
            fly(pilot, 1 / 30, above, t0)
        assert pilot.pilot.state == "released"
        time.sleep(0.1)
        released = len(vehicle.setpoints())
        fly(pilot, 0.3, above, t0)
        time.sleep(0.1)
        assert len(vehicle.setpoints()) == released
    late = vehicle.setpoints()[holding:released]
    assert len(late) > 10
    assert all((msg.vx, msg.vy, msg.vz) == (0, 0, 0) for _, msg in late)
    name = "attitude" if stream == "ATTITUDE" else "position"
    assert any(f"vehicle's {name} is" in r and "hovering, no climb" in r for r in reports)
    assert any(f"{name} is" in r and "its autopilot flies it now" in r for r in reports)


@pytest.mark.parametrize(
    "options",
    [
        ("--mavlink", "udpout:127.0.0.1:9", "--mavlink-pilot", "--mount", "down", "--realtime"),
        ("--crazyflie", "radio://0/80/2M/E7E7E7E7E7", "--mount", "down", "--realtime"),
    ],
)
def test_a_pilot_with_a_downward_camera_is_refused(
    approach_fpv_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    track_argv: Callable[..., list[str]],
    options: tuple[str, ...],
) -> None:
    """The perching pilot climbs towards a target above: with a camera looking down it would
    climb away from a target below, so the command stops before any link opens."""
    code = main(track_argv(approach_fpv_dir, tmp_path / "p.csv", *options))
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1
    assert "perches on a target above the vehicle, so the camera must look up" in err
    assert "points down" in err
    assert not (tmp_path / "p.csv").exists()


def test_target_system_is_checked_and_needs_a_link(
    approach_fpv_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    track_argv: Callable[..., list[str]],
) -> None:
    argv = track_argv(approach_fpv_dir, tmp_path / "p.csv", "--target-system", "7")
    assert main(argv) == 2
    assert "--target-system needs --mavlink" in capsys.readouterr().err
    argv = track_argv(
        approach_fpv_dir,
        tmp_path / "p.csv",
        "--mavlink",
        "udpout:127.0.0.1:9",
        "--target-system",
        "0",
    )
    assert main(argv) == 2
    assert "--target-system" in capsys.readouterr().err


def test_a_vehicle_gone_silent_is_not_told_to_set_its_stream_rates(
    udp_port: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A vehicle that streamed, then stopped sending anything (switched off, out of range):
    its streams are missing because it is, and the link does not ask for them nor blame its
    stream rates."""
    monkeypatch.setattr(mavlink_link, "STREAM_RETRY_S", 0.2)
    monkeypatch.setattr(mavlink_link, "SILENT_VEHICLE_S", 0.5)
    vehicle = Vehicle(udp_port, ARDUPILOT, GUIDED)
    reports: list[str] = []
    pilot = MavlinkPilot(f"udpout:127.0.0.1:{udp_port}", report=reports.append)
    try:
        wait_for(lambda: pilot.link.vehicle.R_ned_frd is not None)
        vehicle.stop()
        time.sleep(1.0)  # its last HEARTBEAT is over 0.5 s old: it is silent
        asked = pilot.link.stream_requests
        time.sleep(1.0)  # far beyond three stream requests 0.2 s apart
    finally:
        pilot.close()
    assert pilot.link.vehicle.R_ned_frd is not None
    assert not any("though asked" in r for r in reports), reports
    assert pilot.link.stream_requests == asked  # no more asking a silent vehicle


def test_the_pilot_asks_for_its_streams_and_says_why_it_never_took_over(
    udp_port: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A vehicle that sends only heartbeats: the link asks it for ATTITUDE (30) and
    LOCAL_POSITION_NED (32) at 50 Hz with MAV_CMD_SET_MESSAGE_INTERVAL, asks again, says once
    that they never came, and the pilot's summary says why it never took over."""
    monkeypatch.setattr(mavlink_link, "STREAM_RETRY_S", 0.2)
    vehicle = Vehicle(udp_port, ARDUPILOT, GUIDED)
    vehicle.streams = set()
    reports: list[str] = []
    pilot = MavlinkPilot(f"udpout:127.0.0.1:{udp_port}", report=reports.append)
    try:
        wait_for(lambda: any("though asked 3 times" in r for r in reports))
        fly(pilot, 0.2, (0.0, 0.0, 0.6), time.monotonic())
    finally:
        pilot.close()
        vehicle.stop()
    commands = [m for _, m in vehicle.received if m.get_type() == "COMMAND_LONG"]
    # the HEARTBEAT (message 0) is asked for at 10 Hz, which this vehicle does not do
    asked = [m for m in commands if m.param1 != 0]
    assert {(m.command, m.param1, m.param2) for m in commands if m.param1 == 0} == {
        (511, 0, 100000)
    }
    assert {(m.command, m.param1, m.param2) for m in asked} == {
        (511, 30, 20000),
        (511, 32, 20000),
        (511, 105, 20000),
    }
    assert len(asked) == 9  # each stream, three times
    assert all((m.target_system, m.target_component) == (7, 1) for m in asked)
    assert not vehicle.setpoints()
    assert reports[-1] == (
        "MAVLink pilot: never took over (no ATTITUDE and LOCAL_POSITION_NED streaming)"
    )


def test_streams_that_arrive_are_not_asked_again(udp_port: int) -> None:
    with guided(udp_port) as (vehicle, _pilot, _reports):
        time.sleep(2.5)  # past the time a missing stream would be asked for again
    commands = [m for _, m in vehicle.received if m.get_type() == "COMMAND_LONG"]
    asked = [m for m in commands if m.param1 != 0]  # not the HEARTBEAT's rate
    assert len(asked) <= 3  # at most the first request, before the streams were seen


def _command_longs(vehicle: Vehicle, command: int) -> list[Any]:
    return [
        m for _, m in vehicle.received if m.get_type() == "COMMAND_LONG" and m.command == command
    ]


QUICK_LANDING = PilotSettings(on_senses_lost="release", land_after_lost_s=1.5, land_speed_mps=0.5)


def test_a_stalled_camera_lands_the_vehicle_on_a_sensed_touchdown(udp_port: int) -> None:
    """Frames stop after half a second (the source stays open): the pilot's own clock keeps
    the vehicle hearing it, with no gap over 0.2 s, through the hold, lost and landing; it
    disarms once LOCAL_POSITION_NED says the vehicle rests on the floor, not before."""
    with guided(udp_port, settings=QUICK_LANDING) as (vehicle, pilot, reports):
        vehicle.flies = True
        fly(pilot, 0.5, (0.0, 0.0, 0.6), time.monotonic())
        wait_for(lambda: pilot.pilot.state == "landed", seconds=10.0)
        time.sleep(0.1)
    states = [t[2] for t in pilot.pilot.transitions]
    assert states == ["perching", "lost", "landing", "landed"]
    assert any("no frame since" in r for r in reports)
    (disarm,) = _command_longs(vehicle, 400)
    assert disarm.param2 == 0  # a normal disarm: the autopilot's land detector may refuse it
    assert vehicle.disarmed_at_m is not None
    assert vehicle.disarmed_at_m < 0.01
    times = [m._timestamp for _, m in vehicle.setpoints()]
    assert max(np.diff(times)) < 0.2  # the Crazyflie's watchdog bound; 0.05 s by design
    assert not _command_longs(vehicle, 176)  # the landing was ours, not the autopilot's


def test_a_landing_whose_vehicle_does_not_descend_never_disarms_it(udp_port: int) -> None:
    """The vehicle stays 1 m up whatever it is told: descent setpoints go on, and no disarm."""
    with guided(udp_port, settings=QUICK_LANDING) as (vehicle, pilot, _reports):
        fly(pilot, 0.3, (0.0, 0.0, 0.6), time.monotonic())
        wait_for(lambda: pilot.pilot.state == "landing", seconds=5.0)
        time.sleep(1.5)
        assert pilot.pilot.state == "landing"
        landing = [m for _, m in vehicle.setpoints()][-20:]
    assert not _command_longs(vehicle, 400)
    assert all(m.vz == pytest.approx(0.5) for m in landing)  # down, in NED


def test_a_landing_that_loses_the_vehicles_height_hands_it_to_the_autopilots_land(
    udp_port: int,
) -> None:
    with guided(udp_port, settings=QUICK_LANDING) as (vehicle, pilot, reports):
        fly(pilot, 0.3, (0.0, 0.0, 0.6), time.monotonic())
        wait_for(lambda: pilot.pilot.state == "landing", seconds=5.0)
        vehicle.streams.discard("LOCAL_POSITION_NED")
        wait_for(lambda: pilot.pilot.state == "released")
        wait_for(lambda: vehicle.mode == 9)
    (land,) = _command_longs(vehicle, 176)
    assert (land.param1, land.param2) == (1, 9)  # custom mode: ArduCopter LAND
    assert not _command_longs(vehicle, 400)
    assert any("the autopilot's LAND lands it" in r for r in reports)


def test_a_rebooted_autopilot_is_followed_once_its_old_clock_has_stopped(udp_port: int) -> None:
    """The autopilot's clock since boot restarts at 1 s: its samples are refused until the
    old clock has been silent for half a second (the pilot hovers meanwhile), then taken; the
    link says so once and measures TIMESYNC anew."""
    with guided(udp_port) as (vehicle, pilot, reports):
        t0 = time.monotonic()
        fly(pilot, 0.3, (0.0, 0.0, 0.6), t0)
        vehicle.boot_offset_ms = int(time.monotonic() * 1000) - 1000
        fly(pilot, 1.5, (0.0, 0.0, 0.6), t0)
        assert pilot.pilot.state == "perching"
    gate = pilot.vehicle.gate
    assert gate.reboots == 1
    assert gate.refused["out of order"] >= 20  # half a second of both streams at 50 Hz
    assert pilot.link.timesync.resets >= 1
    assert sum("the autopilot rebooted" in r for r in reports) == 1
    assert any("hovering, no climb" in r for r in reports)


@pytest.mark.parametrize(
    "link",
    [
        ("--mavlink", "udpout:127.0.0.1:9", "--mavlink-pilot"),
        ("--crazyflie", "radio://0/80/2M/E7E7E7E7E7"),
    ],
)
def test_a_recording_flies_a_vehicle_only_in_real_time(
    approach_fpv_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    track_argv: Callable[..., list[str]],
    link: tuple[str, ...],
) -> None:
    """A recorded folder replayed as fast as it decodes would fly a live vehicle on a clock
    several times too fast: refused in one line before any link opens, unless --realtime."""
    for pace in ((), ("--rate", "7")):
        code = main(track_argv(approach_fpv_dir, tmp_path / "p.csv", *link, *pace))
        assert code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1
        assert (
            f"a recording flies a live vehicle ({link[-1] if link[0] == '--mavlink' else link[0]})"
            in err[0]
        )
        assert "add --realtime" in err[0]
    assert not (tmp_path / "p.csv").exists()


def test_a_vehicle_landing_on_a_roof_is_disarmed_on_its_own_land_detector(udp_port: int) -> None:
    """Its floor is 40 cm above its local origin, so its height never reads near zero: the
    pilot's touchdown rule cannot tell, the autopilot's land detector (EXTENDED_SYS_STATE
    ON_GROUND) can, and ends the landing with a normal disarm there."""
    with guided(udp_port, settings=QUICK_LANDING) as (vehicle, pilot, reports):
        vehicle.flies, vehicle.floor_m, vehicle.land_detector = True, 0.4, True
        fly(pilot, 0.3, (0.0, 0.0, 0.6), time.monotonic())
        wait_for(lambda: pilot.pilot.state == "landed", seconds=12.0)
        time.sleep(0.1)
    (disarm,) = _command_longs(vehicle, 400)
    assert disarm.param2 == 0
    assert vehicle.disarmed_at_m == pytest.approx(0.4)
    assert any("land detector says landed" in r for r in reports)


def test_tracking_that_ends_mid_landing_hands_the_vehicle_to_land(udp_port: int) -> None:
    """The source ends while the pilot is landing: not a hover where the landing left the
    vehicle, but the autopilot's own LAND."""
    with guided(udp_port, settings=QUICK_LANDING) as (vehicle, pilot, reports):
        fly(pilot, 0.3, (0.0, 0.0, 0.6), time.monotonic())
        wait_for(lambda: pilot.pilot.state == "landing", seconds=5.0)
    wait_for(lambda: vehicle.mode == 9)
    assert pilot.pilot.state == "released"
    (land,) = _command_longs(vehicle, 176)
    assert (land.param1, land.param2) == (1, 9)
    assert any("while landing: the autopilot's LAND lands the vehicle" in r for r in reports)
    assert not any("a hover setpoint" in r for r in reports)


def test_the_accelerometers_push_is_leaned_against_and_a_vehicle_without_one_is_flown_without(
    udp_port: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """HIGHRES_IMU's accelerometer along the body's x and y is the air's push: with 0.6 m/s^2
    forward (north: the vehicle is level, heading north) the setpoints lean against it by
    push / the velocity loop's gain; a vehicle that never sends it is flown as before, and the
    link says so once. (No disturbance observer and no lateral integral: this vehicle flies
    no setpoint, which they would wind up on.)"""
    monkeypatch.setattr(mavlink_link, "STREAM_RETRY_S", 0.2)
    settings = ControllerSettings(observer_rate=0.0, k_i_xy=0.0)
    north: dict[str, float] = {}
    for pushed in (False, True):
        controller = PerchingController(settings)
        with guided(udp_port, controller=controller) as (vehicle, pilot, reports):
            if pushed:
                vehicle.push_frd_mps2 = (0.6, 0.0)
                wait_for(lambda: pilot.specific_force() is not None)
                wait_for(lambda: float(pilot.specific_force()[0]) > 0.5)  # type: ignore[index]
            else:
                vehicle.streams.discard("HIGHRES_IMU")
                wait_for(lambda: any("HIGHRES_IMU" in r for r in reports))
                assert pilot.specific_force() is None
            start = len(vehicle.setpoints())
            fly(pilot, 0.6, (0.0, 0.0, 0.6), time.monotonic())
            sent = [msg for _, msg in vehicle.setpoints()[start:]]
        assert len(sent) > 10
        north[str(pushed)] = float(np.mean([msg.vx for msg in sent[len(sent) // 2 :]]))
        if not pushed:
            (said,) = [r for r in reports if "HIGHRES_IMU" in r]
            assert "flown without its accelerometer" in said
    lean = north["True"] - north["False"]
    assert lean == pytest.approx(-0.6 / settings.onboard_velocity_gain, rel=0.1)


def test_an_accelerometer_that_stops_is_flown_without_and_nothing_else_changes(
    udp_port: int,
) -> None:
    """HIGHRES_IMU stops mid-climb while ATTITUDE and LOCAL_POSITION_NED go on: the push is no
    longer fed forward (its last sample ages out after ``odometry_max_age_s``), and the pilot
    neither hovers nor hands the vehicle back: the accelerometer is not one of its senses."""
    above = (0.0, 0.0, 0.6)
    with guided(udp_port) as (vehicle, pilot, reports):
        vehicle.push_frd_mps2 = (0.6, 0.0)
        wait_for(lambda: pilot.specific_force() is not None)
        t0 = time.monotonic()
        fly(pilot, 0.5, above, t0)
        vehicle.streams.discard("HIGHRES_IMU")
        start = len(vehicle.setpoints())
        fly(pilot, 1.5, above, t0)
        state = pilot.pilot.state
        assert pilot.specific_force() is None
    late = [msg for _, msg in vehicle.setpoints()[start:]]
    assert state == "perching"
    assert len(late) > 30
    # still climbing (NED z down) up to the one zero setpoint ``close`` sends
    assert all(msg.vz < -0.05 for msg in late[-11:-1])
    assert (late[-1].vx, late[-1].vy, late[-1].vz) == (0, 0, 0)
    assert not any("hovering" in r or "autopilot flies it now" in r for r in reports)
