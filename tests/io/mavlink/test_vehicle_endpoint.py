"""The vehicle's end of a MAVLink link, heard by the project's own companion link: the
autopilot it says it is, its mode and arming, its attitude and position in NED, its
accelerometer in FRD, the stream rates asked of it and TIMESYNC."""

import math
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from perchpose.geometry import rot_z
from perchpose.io.mavlink.landing_target import R_ned_frd_from_euler
from perchpose.io.mavlink.link import MavlinkLink
from perchpose.io.mavlink.vehicle_endpoint import F, VehicleEndpoint, euler_ned_frd

pytest.importorskip("pymavlink")


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def test_attitude_angles_turn_back_into_the_body_attitude():
    rng = np.random.default_rng(3)
    for _ in range(20):
        yaw, roll = rng.uniform(-3.0, 3.0), rng.uniform(-0.5, 0.5)
        R_world_body = rot_z(yaw) @ _rot_x(roll)
        R_ned_frd = R_ned_frd_from_euler(*euler_ned_frd(R_world_body))
        assert np.allclose(F @ R_ned_frd @ F, R_world_body, atol=1e-9)


class Served:
    """An endpoint served on a thread as the sim-vehicle serves it: a vehicle 1 m up, 0.2 m
    north and 0.1 m west of its origin, heading 30 deg left of north, climbing at 0.1 m/s,
    LOITER (custom mode 5), armed, its accelerometer reading a push of 0.3 m/s^2 forward and
    0.2 m/s^2 left (FLU); its ATTITUDE stream off until asked for."""

    R = rot_z(math.radians(30.0))
    p = np.array([0.2, 0.1, 1.0])
    v = np.array([0.0, 0.0, 0.1])
    f_body = np.array([0.3, 0.2, 9.81])

    def __init__(self, port: int, autopilot: int = 3) -> None:
        self.endpoint = VehicleEndpoint(f"udpin:127.0.0.1:{port}", autopilot=autopilot)
        self.endpoint.interval_s["ATTITUDE"] = math.inf
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        start = time.monotonic()
        while not self._stop.is_set():
            list(self.endpoint.messages())
            now = time.monotonic() - start
            self.endpoint.heartbeat(now, 5, armed=True)
            self.endpoint.state(
                now, self.R, np.zeros(3), self.p, self.v, on_ground=False, f_body_mps2=self.f_body
            )
            time.sleep(0.005)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        self.endpoint.close()


@pytest.fixture
def served(udp_port: int) -> Iterator[Served]:
    vehicle = Served(udp_port)
    yield vehicle
    vehicle.stop()


def _until(check, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if check():
            return True
        time.sleep(0.02)
    return False


def test_a_companion_hears_the_autopilot_its_state_in_ned_and_its_clock(
    served: Served, udp_port: int
):
    link = MavlinkLink(
        f"udpout:127.0.0.1:{udp_port}",
        streams=("ATTITUDE", "LOCAL_POSITION_NED", "HIGHRES_IMU"),
        stream_hz=25.0,
    )
    try:
        vehicle = link.vehicle
        assert _until(lambda: vehicle.R_ned_frd is not None and vehicle.p_ned_m is not None)
        assert _until(lambda: vehicle.f_frd_mps2 is not None)
        assert np.allclose(vehicle.f_frd_mps2, [0.3, -0.2, -9.81], atol=1e-5)  # FRD
        assert vehicle.autopilot == 3
        assert vehicle.custom_mode == 5
        assert vehicle.armed
        assert np.allclose(F @ vehicle.R_ned_frd @ F, Served.R, atol=1e-6)
        assert np.allclose(vehicle.p_ned_m, [0.2, -0.1, -1.0], atol=1e-6)
        assert np.allclose(vehicle.v_ned_mps, [0.0, 0.0, -0.1], atol=1e-6)
        # the stream came at the rate the companion asked for; its TIMESYNC was answered
        assert served.endpoint.interval_s["ATTITUDE"] == pytest.approx(0.04)
        assert link.stream_requests >= 1
        assert _until(lambda: link.timesync.offset_ns is not None)
        assert served.endpoint.received["HEARTBEAT"] > 0
    finally:
        link.close()


@pytest.mark.parametrize("autopilot", [3, 12])
def test_the_vehicles_heartbeat_is_asked_for_at_ten_hertz(
    udp_port: int, autopilot: int, monkeypatch: pytest.MonkeyPatch
):
    """The HEARTBEAT is the only message that says the vehicle's mode: the link asks for it at
    10 Hz. ArduPilot sends it so (a mode change is heard within 0.1 s); PX4 keeps 1 Hz, and
    after three tries the link says so, once."""
    from perchpose.io.mavlink import link as link_module

    monkeypatch.setattr(link_module, "STREAM_RETRY_S", 1.2)  # a 1 s HEARTBEAT comes in it
    served = Served(udp_port, autopilot)
    said: list[str] = []
    link = MavlinkLink(f"udpout:127.0.0.1:{udp_port}", heartbeat_hz=10.0, report=said.append)
    try:
        vehicle = link.vehicle
        if autopilot == 3:
            assert _until(lambda: served.endpoint.interval_s["HEARTBEAT"] == pytest.approx(0.1))
            assert _until(lambda: vehicle.heartbeat_period_s < 0.15)
            time.sleep(1.5)
            assert vehicle.heartbeat_period_s < 0.15
            assert link.heartbeat_requests == 1
            assert not said
        else:
            assert _until(lambda: any("keeps its HEARTBEAT" in line for line in said))
            assert link.heartbeat_requests == 3
            assert served.endpoint.interval_s["HEARTBEAT"] == 1.0
            time.sleep(1.0)
            assert link.heartbeat_requests == 3  # no more asking
    finally:
        link.close()
        served.stop()
    with pytest.raises(link_module.LinkError, match="HEARTBEAT rate must be 1 to 50 Hz"):
        MavlinkLink(f"udpout:127.0.0.1:{udp_port}", heartbeat_hz=0.0)


def test_an_accelerometer_reading_that_is_no_reading_is_dropped() -> None:
    """HIGHRES_IMU with a NaN or beyond 16 g is refused whole; the last good one stays."""
    from pymavlink.dialects.v20 import common

    from perchpose.io.mavlink.link import VehicleState

    state = VehicleState()
    zero = (0.0,) * 10

    def imu(ax: float, ay: float, az: float) -> object:
        return common.MAVLink_highres_imu_message(0, ax, ay, az, *zero, 7)

    assert state.heard(imu(0.1, -0.2, -9.8), now=1.0)
    assert not state.heard(imu(float("nan"), 0.0, -9.8), now=2.0)
    assert not state.heard(imu(0.0, 0.0, -200.0), now=3.0)
    assert state.f_frd_mps2 is not None
    assert np.allclose(state.f_frd_mps2, [0.1, -0.2, -9.8])
    assert state.imu_age_s(5.0) == pytest.approx(4.0)
    assert state.rejected == 2
