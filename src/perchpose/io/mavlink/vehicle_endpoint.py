"""The vehicle's side of a MAVLink link: what an autopilot sends a companion computer and how
it answers one, for a simulated vehicle (``perchpose sim-vehicle``).

Sends HEARTBEAT (MAV_TYPE_QUADROTOR, the autopilot's id, armed flag and custom mode),
ATTITUDE, LOCAL_POSITION_NED, HIGHRES_IMU (its accelerometer and gyro) and
EXTENDED_SYS_STATE (its land detector) at the rates asked
for with MAV_CMD_SET_MESSAGE_INTERVAL (50 Hz until asked), answers TIMESYNC requests with
its time since boot, and acknowledges each COMMAND_LONG with COMMAND_ACK. Times on the wire
are since this endpoint's start (``time_boot_ms``), as an autopilot's are since its boot.
Frames: the simulation's world is z up (NWU) and its body FLU; the wire's are NED and FRD
(``F`` turns one into the other).

Every message received is counted by type (``received``); LANDING_TARGET is kept for the
summary. Nothing received ends the endpoint: a message it cannot use is counted and ignored.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import LinkError
from perchpose.io.mavlink.link import check_url, mavutil_module

Array = NDArray[np.float64]

F = np.diag([1.0, -1.0, -1.0])  # NWU <-> NED and FLU <-> FRD
MAV_TYPE_QUADROTOR = 2
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_STATE_STANDBY, MAV_STATE_ACTIVE = 3, 4
MAV_LANDED_STATE_ON_GROUND, MAV_LANDED_STATE_IN_AIR = 1, 2
MAV_RESULT_ACCEPTED, MAV_RESULT_DENIED, MAV_RESULT_UNSUPPORTED = 0, 2, 3
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
STREAMS = {
    0: "HEARTBEAT",
    30: "ATTITUDE",
    32: "LOCAL_POSITION_NED",
    105: "HIGHRES_IMU",
    245: "EXTENDED_SYS_STATE",
}
DEFAULT_INTERVAL_S = {
    "HEARTBEAT": 1.0,
    "ATTITUDE": 0.02,
    "LOCAL_POSITION_NED": 0.02,
    "HIGHRES_IMU": 0.02,
    "EXTENDED_SYS_STATE": 0.2,
}
HIGHRES_IMU_ACC_GYRO = 0b111111  # fields_updated: the accelerometer's and the gyro's axes


def euler_ned_frd(R_world_body: Array) -> tuple[float, float, float]:
    """ATTITUDE's roll, pitch, yaw (ZYX, FRD in NED) of a body attitude in the world (FLU in
    NWU)."""
    R = F @ np.asarray(R_world_body, np.float64) @ F
    pitch = -math.asin(max(-1.0, min(1.0, float(R[2, 0]))))
    roll = math.atan2(float(R[2, 1]), float(R[2, 2]))
    yaw = math.atan2(float(R[1, 0]), float(R[0, 0]))
    return roll, pitch, yaw


class VehicleEndpoint:
    """The vehicle's end of a pymavlink connection (``udpin:HOST:PORT`` by default: it waits
    for the companion's first packet and answers where it came from, as a UDP endpoint of
    ArduPilot's or PX4's SITL does). ``autopilot``: MAV_AUTOPILOT (3 ArduPilot, 12 PX4)."""

    def __init__(self, url: str, autopilot: int, system_id: int = 1) -> None:
        self.url = check_url(url)
        mavutil = mavutil_module()
        try:
            self._conn: Any = mavutil.mavlink_connection(
                self.url, source_system=system_id, source_component=1
            )
        except OSError as exc:
            raise LinkError(f"MAVLink {url}: cannot open ({exc.strerror or exc})") from exc
        self.autopilot = autopilot
        self.system_id = system_id
        self._start_ns = time.monotonic_ns()
        self.interval_s = dict(DEFAULT_INTERVAL_S)
        self._due_s: dict[str, float] = {}
        self._next_heartbeat_s = 0.0
        self.received: Counter[str] = Counter()
        self.peer = False  # a companion has been heard (until then nothing can be sent)
        self.landing_targets = 0

    def boot_ms(self) -> int:
        return ((time.monotonic_ns() - self._start_ns) // 1_000_000) & 0xFFFFFFFF

    def messages(self) -> Iterator[Any]:
        """Every message waiting, without blocking; TIMESYNC requests and message intervals
        are handled here and not handed on."""
        while True:
            msg = self._conn.recv_match(blocking=False)
            if msg is None:
                return
            kind = msg.get_type()
            self.received[kind] += 1
            if kind == "BAD_DATA":
                continue
            self.peer = True
            if kind == "TIMESYNC":
                self._timesync(msg)
            elif kind == "LANDING_TARGET":
                self.landing_targets += 1
            elif kind == "COMMAND_LONG" and msg.command == MAV_CMD_SET_MESSAGE_INTERVAL:
                self._interval(msg)
            else:
                yield msg

    def _timesync(self, msg: Any) -> None:
        if msg.tc1 == 0 and msg.ts1 > 0:
            since_boot_ns = time.monotonic_ns() - self._start_ns
            self._conn.mav.timesync_send(since_boot_ns, msg.ts1)

    def _interval(self, msg: Any) -> None:
        name = STREAMS.get(int(msg.param1))
        # ArduPilot sets its HEARTBEAT's rate as any message's; PX4 keeps it at 1 Hz
        px4_heartbeat = name == "HEARTBEAT" and self.autopilot != MAV_AUTOPILOT_ARDUPILOTMEGA
        if name is None or px4_heartbeat:
            self.ack(MAV_CMD_SET_MESSAGE_INTERVAL, MAV_RESULT_UNSUPPORTED)
            return
        interval_us = float(msg.param2)
        if interval_us == -1:
            self.interval_s[name] = math.inf  # stop it
        elif interval_us == 0:
            self.interval_s[name] = DEFAULT_INTERVAL_S[name]
        elif interval_us > 0:
            self.interval_s[name] = interval_us / 1e6
        self.ack(MAV_CMD_SET_MESSAGE_INTERVAL, MAV_RESULT_ACCEPTED)

    def ack(self, command: int, result: int) -> None:
        if self.peer:
            self._conn.mav.command_ack_send(command, result)

    def due(self, name: str, now_s: float) -> bool:
        """Time to send stream ``name`` again (and it is counted as sent)."""
        if not self.peer or math.isinf(self.interval_s[name]):
            return False
        if now_s < self._due_s.get(name, 0.0):
            return False
        self._due_s[name] = now_s + self.interval_s[name]
        return True

    def heartbeat(self, now_s: float, custom_mode: int, armed: bool, at_once: bool = False) -> None:
        """A HEARTBEAT at its interval (a second unless asked otherwise; never, asked so), and
        ``at_once`` (a mode or arming that changed)."""
        if not self.peer or (now_s < self._next_heartbeat_s and not at_once):
            return
        self._next_heartbeat_s = now_s + self.interval_s["HEARTBEAT"]
        base = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
        state = MAV_STATE_ACTIVE if armed else MAV_STATE_STANDBY
        self._conn.mav.heartbeat_send(MAV_TYPE_QUADROTOR, self.autopilot, base, custom_mode, state)

    def state(
        self,
        now_s: float,
        R_world_body: Array,
        omega_body_rad_s: Array,
        p_world_m: Array,
        v_world_mps: Array,
        on_ground: bool,
        f_body_mps2: Array | None = None,
    ) -> None:
        """The streams that are due: attitude, local position (NED), the IMU (the specific
        force ``f_body_mps2`` in FLU, none without it) and landed state."""
        t_ms = self.boot_ms()
        if self.due("ATTITUDE", now_s):
            roll, pitch, yaw = euler_ned_frd(R_world_body)
            p, q, r = (F @ np.asarray(omega_body_rad_s, np.float64)).tolist()
            self._conn.mav.attitude_send(t_ms, roll, pitch, yaw, p, q, r)
        if self.due("LOCAL_POSITION_NED", now_s):
            x, y, z = (F @ np.asarray(p_world_m, np.float64)).tolist()
            vx, vy, vz = (F @ np.asarray(v_world_mps, np.float64)).tolist()
            self._conn.mav.local_position_ned_send(t_ms, x, y, z, vx, vy, vz)
        if f_body_mps2 is not None and self.due("HIGHRES_IMU", now_s):
            ax, ay, az = (F @ np.asarray(f_body_mps2, np.float64)).tolist()
            p, q, r = (F @ np.asarray(omega_body_rad_s, np.float64)).tolist()
            t_us = t_ms * 1000
            self._conn.mav.highres_imu_send(
                t_us, ax, ay, az, p, q, r, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, HIGHRES_IMU_ACC_GYRO
            )
        if self.due("EXTENDED_SYS_STATE", now_s):
            landed = MAV_LANDED_STATE_ON_GROUND if on_ground else MAV_LANDED_STATE_IN_AIR
            self._conn.mav.extended_sys_state_send(0, landed)

    def close(self) -> None:
        self._conn.close()
