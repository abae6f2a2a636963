"""Perching with an autopilot, checked at the autopilot's rules against a pymavlink endpoint on
loopback that plays the vehicle: HEARTBEAT with its mode, ATTITUDE and LOCAL_POSITION_NED at
50 Hz, and what it receives kept with the mode it was in."""

import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from perchpose.cli import main
from perchpose.io.mavlink import mavutil_module
from perchpose.io.mavlink_link import MavlinkLink
from perchpose.io.mavlink_pilot import MavlinkPilot, SetpointCommander
from perchpose.values import Estimate

ARDUPILOT, PX4 = 3, 12
LOITER, GUIDED = 5, 4  # ArduCopter custom modes
POSCTL, OFFBOARD = 3 << 16, 6 << 16  # PX4 main modes in custom_mode's third byte
ARMED = 128 | 1  # MAV_MODE_FLAG_SAFETY_ARMED | MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


class Vehicle:
    """An autopilot on ``udpin``: level, still, 1 m up, in ``mode``; heartbeats at 10 Hz
    (and at once on a mode change) until ``silent``."""

    def __init__(self, port: int, autopilot: int, mode: int, system: int = 7) -> None:
        self.conn = mavutil_module().mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=system, source_component=1
        )
        self.autopilot = autopilot
        self.mode = mode
        self.armed = True
        self.silent = False
        self.received: list[tuple[int, Any]] = []  # (the mode it arrived in, message)
        self._stop = threading.Event()
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
                self.received.append((self.mode, msg))
            now = time.monotonic()
            if now >= next_beat:
                next_beat = now + 0.1
                self._beat()
            if self.received and now >= next_state:
                next_state = now + 0.02
                self.conn.mav.attitude_send(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
                self.conn.mav.local_position_ned_send(0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0)

    def setpoints(self) -> list[tuple[int, Any]]:
        return [
            (m, msg)
            for m, msg in self.received
            if msg.get_type() == "SET_POSITION_TARGET_LOCAL_NED"
        ]

    def stop(self) -> None:
        time.sleep(0.2)
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
        commander.send_velocity_world_setpoint(0.1, 0.2, 0.3, 10.0)
        commander.send_stop_setpoint()
        force[0] = True
        commander.send_stop_setpoint()
        allowed[0] = False
        commander.send_velocity_world_setpoint(0.1, 0.2, 0.3, 10.0)
        commander.send_stop_setpoint()
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
