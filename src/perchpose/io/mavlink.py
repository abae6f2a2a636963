"""Sending the estimate to PX4 or ArduPilot as MAVLink LANDING_TARGET messages.

Needs the ``mavlink`` extra (``pip install perchpose[mavlink]``). LANDING_TARGET's position
fields are MAVLink 2 extensions, so this module sets ``MAVLINK20=1`` before pymavlink is
imported (and switches pymavlink's dialect to MAVLink 2 if it was imported without it).

One ``LandingTargetSink`` owns one connection, and only its own thread touches it: the thread
opens the link, sends the LANDING_TARGET messages ``send`` queues, sends a HEARTBEAT every
second (an onboard computer: ``MAV_TYPE_ONBOARD_CONTROLLER``, component
``MAV_COMP_ID_ONBOARD_COMPUTER``), reads the vehicle's ATTITUDE and LOCAL_POSITION_NED (needed
for ``frame="local_ned"``), answers the autopilot's TIMESYNC requests and sends its own every
second (``perchpose.io.timesync``: once answered, ``time_usec`` is the frame's grab time on
the autopilot's clock) and reopens a link that failed, so tracking never waits on the
network. A link that cannot be opened or goes down (a TCP peer that closes included) is
reported once through ``report``; estimates arriving meanwhile are dropped, and tracking goes
on. pymavlink's own messages about its TCP socket never reach stdout: the sink detects a
closed peer itself and reconnects on its own schedule.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from perchpose.control.mount import default_T_body_camera
from perchpose.errors import LinkError
from perchpose.geometry import check_transform
from perchpose.io.landing_target import (
    FRAMES,
    LandingTarget,
    R_ned_frd_from_euler,
    check_line_of_sight,
    landing_target,
)
from perchpose.io.timesync import TimeSync
from perchpose.target import TargetSpec
from perchpose.values import Estimate

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

URL_PREFIXES = ("udpin:", "udpout:", "udp:", "udpbcast:", "tcp:", "tcpin:")
# MAVLink enum values (common.xml); kept here so that the module imports without pymavlink
MAV_FRAME_IDS = {"local_ned": 1, "body_frd": 12}
LANDING_TARGET_TYPE_VISION_FIDUCIAL = 2
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4
MAV_COMP_ID_ONBOARD_COMPUTER = 191
# LANDING_TARGET messages waiting for the link's thread; a link this far behind drops the oldest
QUEUE_LENGTH = 8


def mavutil_module() -> Any:
    """pymavlink's ``mavutil``, speaking MAVLink 2."""
    os.environ.setdefault("MAVLINK20", "1")
    try:
        from pymavlink import mavutil
    except ImportError as exc:
        raise LinkError("MAVLink needs pymavlink: pip install 'perchpose[mavlink]'") from exc
    if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
        os.environ["MAVLINK20"] = "1"
        mavutil.set_dialect(mavutil.current_dialect)
    return mavutil


def _peer_closed() -> None:
    raise ConnectionResetError("closed by the peer")


def _landing_target_send(mav: Any, *, msg: LandingTarget) -> None:
    mav.landing_target_send(
        msg.time_usec,
        0,
        MAV_FRAME_IDS[msg.frame],
        msg.angle_x_rad,
        msg.angle_y_rad,
        msg.distance_m,
        msg.size_x_rad,
        msg.size_y_rad,
        msg.x_m,
        msg.y_m,
        msg.z_m,
        list(msg.q_wxyz),
        LANDING_TARGET_TYPE_VISION_FIDUCIAL,
        1,
    )


def _timesync_send(mav: Any, *, tc1: int, ts1: int) -> None:
    mav.timesync_send(tc1, ts1)


def check_url(url: str) -> str:
    """A pymavlink connection string: ``udpout:host:port`` and the other network forms, or a
    serial device with an optional baud rate (``/dev/ttyUSB0,57600``)."""
    if url.startswith(URL_PREFIXES):
        rest = url.split(":", 1)[1]
        host, _, port = rest.rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise LinkError(f"MAVLink URL {url!r}: expected {url.split(':', 1)[0]}:HOST:PORT")
        return url
    device, _, baud = url.partition(",")
    if device.startswith(("/", "COM")) and (not baud or baud.isdigit()):
        return url
    raise LinkError(
        f"MAVLink URL {url!r}: expected udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT "
        "or a serial device such as /dev/ttyUSB0,57600"
    )


@dataclass
class VehicleState:
    """What the sink has heard from the vehicle."""

    R_ned_frd: Array | None = None
    p_ned_m: Array | None = None
    attitude_t_s: float = float("nan")
    position_t_s: float = float("nan")


class LandingTargetSink:
    """Sends one LANDING_TARGET per valid estimate over a pymavlink connection.

    url : pymavlink connection string. frame : ``body_frd`` (ArduPilot) or ``local_ned`` (PX4).
    T_body_camera : the camera's mounting on the body (FLU), default
    ``control.default_T_body_camera()``. target : sets the angular size fields.
    time_offset_s : added to the frame times for ``time_usec`` until TIMESYNC has mapped this
    computer's clock to the autopilot's (or for estimates without ``grabbed_s``); then
    ``time_usec`` is ``Estimate.grabbed_s`` on the autopilot's clock. timesync_period_s : how
    often a TIMESYNC request is sent (0: never; requests from the vehicle are answered all the
    same). max_age_s : an estimate whose
    newest measurement is older than this (``Estimate.age_s``) is not sent; default 0.5 s, well
    inside the autopilots' own LANDING_TARGET timeouts (ArduPilot 2 s, PX4 ``PLD_BTOUT`` 5 s).
    report : receives the one-line link reports (default: the ``perchpose.io.mavlink`` logger).
    """

    def __init__(
        self,
        url: str,
        *,
        frame: str = "body_frd",
        T_body_camera: Array | None = None,
        target: TargetSpec | None = None,
        source_system: int = 1,
        source_component: int = MAV_COMP_ID_ONBOARD_COMPUTER,
        time_offset_s: float = 0.0,
        heartbeat_period_s: float = 1.0,
        timesync_period_s: float = 1.0,
        retry_period_s: float = 2.0,
        position_max_age_s: float = 1.0,
        max_age_s: float = 0.5,
        report: Callable[[str], None] | None = None,
    ) -> None:
        if frame not in FRAMES:
            raise LinkError(f"unknown MAVLink frame {frame!r} (choose {', '.join(FRAMES)})")
        self.url = check_url(url)
        self.frame = frame
        try:
            self.T_body_camera = check_transform(
                default_T_body_camera() if T_body_camera is None else T_body_camera,
                "T_body_camera",
            )
        except ValueError as exc:
            raise LinkError(str(exc)) from exc
        check_line_of_sight(self.T_body_camera, frame)
        self.target_side_m = (target or TargetSpec.paper()).markers[0].side_m
        self.source_system = source_system
        self.source_component = source_component
        self.time_offset_s = time_offset_s
        self.heartbeat_period_s = heartbeat_period_s
        self.timesync_period_s = timesync_period_s
        self.timesync = TimeSync()
        self._next_timesync = 0.0
        self.retry_period_s = retry_period_s
        self.position_max_age_s = position_max_age_s
        if not max_age_s > 0:
            raise LinkError(f"max_age_s must be positive, got {max_age_s}")
        self.max_age_s = max_age_s
        self.refused = 0
        self._refused_reported = False
        self.report = report or log.warning
        self.vehicle = VehicleState()
        self.sent = 0
        self.dropped = 0
        self._mavutil = mavutil_module()
        self._lock = threading.Lock()
        self._conn: Any = None
        self._down = False
        self._down_reported = False
        self._no_attitude_reported = False
        self._next_retry = 0.0
        self._next_heartbeat = 0.0
        self._queue: deque[LandingTarget] = deque()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._service, name="mavlink", daemon=True)
        self._thread.start()

    # -- the link -------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        return self._conn is not None

    def _open(self) -> None:
        try:
            conn = self._mavutil.mavlink_connection(
                self.url,
                source_system=self.source_system,
                source_component=self.source_component,
                autoreconnect=False,
                retries=0,  # TCP: one attempt; the service thread retries on its schedule
            )
        except Exception as exc:  # pymavlink raises whatever the transport raises
            self._link_down(f"cannot open {self.url}: {exc}")
            return
        if self.url.startswith("tcp:"):
            # pymavlink prints and carries on when a TCP peer closes; make it an error instead
            conn.handle_eof = _peer_closed
            conn.handle_disconnect = _peer_closed
        with self._lock:
            self._conn = conn
            self._down = False
        self._next_heartbeat = 0.0
        if self._down_reported:
            self.report(f"MAVLink {self.url}: link up again")
            self._down_reported = False

    def _link_down(self, why: str) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except Exception:  # the link is already broken; closing is best effort
                log.debug("closing %s failed", self.url, exc_info=True)
        with self._lock:
            self._conn = None
            self._down = True
            self.dropped += len(self._queue)
            self._queue.clear()
        self._next_retry = time.monotonic() + self.retry_period_s
        if not self._down_reported:
            self.report(
                f"MAVLink {why}; retrying every {self.retry_period_s:g} s, tracking goes on"
            )
            self._down_reported = True

    def _send(self, send: Callable[[Any], None], what: str) -> bool:
        """Send on the service thread; a transport error takes the link down."""
        if self._conn is None:
            return False
        try:
            send(self._conn.mav)
        except OSError as exc:
            self._link_down(f"{self.url} down while sending {what}: {exc}")
            return False
        return True

    def _drain(self) -> None:
        while True:
            with self._lock:
                if not self._queue:
                    return
                msg = self._queue.popleft()
            sent = self._send(partial(_landing_target_send, msg=msg), "LANDING_TARGET")
            with self._lock:
                if not sent:  # the link went down with this message in hand
                    self.dropped += 1
                    return
                self.sent += 1

    def _service(self) -> None:
        while True:
            stopping = self._stop.is_set()
            now = time.monotonic()
            if self._conn is None:
                if stopping:
                    break
                if now >= self._next_retry:
                    self._open()
            else:
                self._drain()
                if stopping:
                    break
                if now >= self._next_heartbeat:
                    self._next_heartbeat = now + self.heartbeat_period_s
                    self._send(self._heartbeat, "HEARTBEAT")
                if self.timesync_period_s > 0 and now >= self._next_timesync:
                    self._next_timesync = now + self.timesync_period_s
                    tc1, ts1 = self.timesync.request()
                    self._send(partial(_timesync_send, tc1=tc1, ts1=ts1), "TIMESYNC")
                self._receive()
            self._wake.wait(0.01)
            self._wake.clear()
        with self._lock:
            self.dropped += len(self._queue)
            self._queue.clear()

    def _heartbeat(self, mav: Any) -> None:
        mav.heartbeat_send(
            MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE
        )

    def _receive(self) -> None:
        for _ in range(100):
            if self._conn is None:
                return
            try:
                msg = self._conn.recv_match(
                    type=["ATTITUDE", "LOCAL_POSITION_NED", "TIMESYNC"], blocking=False
                )
            except OSError as exc:
                self._link_down(f"{self.url} down while reading: {exc}")
                return
            if msg is None:
                return
            now = time.monotonic()
            if msg.get_type() == "TIMESYNC":
                answer = self.timesync.handle(int(msg.tc1), int(msg.ts1))
                if answer is not None:
                    self._send(partial(_timesync_send, tc1=answer[0], ts1=answer[1]), "TIMESYNC")
            elif msg.get_type() == "ATTITUDE":
                self.vehicle.R_ned_frd = R_ned_frd_from_euler(msg.roll, msg.pitch, msg.yaw)
                self.vehicle.attitude_t_s = now
            else:
                self.vehicle.p_ned_m = np.array([msg.x, msg.y, msg.z], dtype=float)
                self.vehicle.position_t_s = now

    # -- estimates ------------------------------------------------------------------------

    def _refuse(self, why: str) -> None:
        self.refused += 1
        if not self._refused_reported:
            self.report(f"MAVLink {self.url}: {why} (reported once; see LandingTargetSink.refused)")
            self._refused_reported = True

    def message(self, estimate: Estimate) -> LandingTarget | None:
        """The LANDING_TARGET this sink would send for ``estimate`` now (None: nothing). Stale
        or non-finite estimates are refused and counted in ``refused``."""
        if not estimate.valid:
            return None
        if not estimate.age_s <= self.max_age_s:
            self._refuse(
                f"estimate at t = {estimate.t_s:.3f} s is {estimate.age_s:.2f} s old "
                f"(limit {self.max_age_s:g} s); not sent"
            )
            return None
        R_ned_frd = p_ned = None
        if self.frame == "local_ned":
            R_ned_frd = self.vehicle.R_ned_frd
            if R_ned_frd is None:
                if not self._no_attitude_reported:
                    self.report(
                        f"MAVLink {self.url}: no ATTITUDE from the vehicle yet; local_ned "
                        "estimates are held back until it arrives"
                    )
                    self._no_attitude_reported = True
                return None
            age = time.monotonic() - self.vehicle.position_t_s
            if self.vehicle.p_ned_m is not None and age < self.position_max_age_s:
                p_ned = self.vehicle.p_ned_m
        shifted = replace(estimate, t_s=estimate.t_s + self.time_offset_s)
        time_usec = None
        if math.isfinite(estimate.grabbed_s):
            time_usec = self.timesync.remote_usec(estimate.grabbed_s)
        try:
            return landing_target(
                shifted,
                self.T_body_camera,
                self.target_side_m,
                frame=self.frame,
                R_ned_frd=R_ned_frd,
                p_ned_vehicle_m=p_ned,
                time_usec=time_usec,
            )
        except LinkError as exc:
            self._refuse(str(exc))
            return None

    def send(self, estimate: Estimate | None) -> bool:
        """Hand LANDING_TARGET for a valid estimate to the link's thread; True if it was
        accepted (False: nothing to send, or the link is down and the estimate is dropped).
        Never waits on the network."""
        if estimate is None:
            return False
        msg = self.message(estimate)
        if msg is None:
            return False
        with self._lock:
            if self._down:
                self.dropped += 1
                return False
            if len(self._queue) >= QUEUE_LENGTH:  # a stalled link: the oldest is least useful
                self._queue.popleft()
                self.dropped += 1
            self._queue.append(msg)
        self._wake.set()
        return True

    def __call__(self, estimate: Estimate | None, t_s: float) -> None:
        """The per-frame hook ``track`` calls."""
        self.send(estimate)

    def close(self) -> None:
        """Send what is queued, stop the service thread and close the connection."""
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=2.0)
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def __enter__(self) -> LandingTargetSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
