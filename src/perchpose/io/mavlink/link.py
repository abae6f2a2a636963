"""One MAVLink connection to a vehicle, served by its own thread.

Needs the ``mavlink`` extra (``pip install perchpose[mavlink]``). LANDING_TARGET's position
fields are MAVLink 2 extensions, so this module sets ``MAVLINK20=1`` before pymavlink is
imported (and switches pymavlink's dialect to MAVLink 2 if it was imported without it).

Only the link's thread touches the connection: it opens the link, sends what ``post`` queues,
sends a HEARTBEAT every second (an onboard computer: ``MAV_TYPE_ONBOARD_CONTROLLER``, component
``MAV_COMP_ID_ONBOARD_COMPUTER``), reads the vehicle's HEARTBEAT, ATTITUDE and
LOCAL_POSITION_NED into ``vehicle``, answers the autopilot's TIMESYNC requests and sends its own
every second (``mavlink.timesync``) and reopens a link that failed, so that whoever posts
never waits on the network. A link that cannot be opened or goes down (a TCP peer that closes
included) is reported once through ``report``; messages posted meanwhile are dropped.
pymavlink's own messages about its TCP socket never reach stdout: the link detects a closed
peer itself and reconnects on its own schedule.

The senders (``landing_target_sink``'s LANDING_TARGET sink, ``pilot``'s
setpoints) are built on it; ``listeners`` are called on the link's thread with each message
received from the vehicle, and ``pollers`` with the time on each turn of its loop.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import LinkError
from perchpose.io.mavlink.landing_target import R_ned_frd_from_euler
from perchpose.io.mavlink.timesync import TimeSync
from perchpose.io.samples import SampleGate

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

URL_PREFIXES = ("udpin:", "udpout:", "udp:", "udpbcast:", "tcp:", "tcpin:")
# MAVLink enum values (common.xml); kept here so that the module imports without pymavlink
MAV_TYPE_GCS = 6
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_COMP_ID_ONBOARD_COMPUTER = 191
MAV_CMD_SET_MESSAGE_INTERVAL = 511
STREAM_IDS = {"ATTITUDE": 30, "LOCAL_POSITION_NED": 32, "HIGHRES_IMU": 105}
# the streams a vehicle is flown without where it does not send them, and what that costs
OPTIONAL_STREAMS = {
    "HIGHRES_IMU": "flown without its accelerometer (no push fed forward; ArduPilot sends it "
    "only in builds with AP_MAVLINK_MSG_HIGHRES_IMU_ENABLED)",
}
MAX_SPECIFIC_FORCE_MPS2 = 160.0  # 16 g: an accelerometer reading beyond is no reading
HEARTBEAT_ID = 0
MAV_LANDED_STATE_ON_GROUND = 1
STREAM_RETRY_S = 2.0  # a stream not arriving this long after it was asked for is asked again
STREAM_TRIES = 3
SILENT_VEHICLE_S = 3.0  # no HEARTBEAT for this long: the vehicle is silent, not its streams
# messages waiting for the link's thread; a link this far behind drops the oldest
QUEUE_LENGTH = 8

Send = Callable[[Any], None]  # given pymavlink's ``conn.mav``, sends one message


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


def _timesync_send(mav: Any, *, tc1: int, ts1: int) -> None:
    mav.timesync_send(tc1, ts1)


def _interval_send(
    mav: Any, *, system: int, component: int, message_id: int, interval_us: int
) -> None:
    """COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL: send ``message_id`` every ``interval_us``."""
    mav.command_long_send(
        system, component, MAV_CMD_SET_MESSAGE_INTERVAL, 0, message_id, interval_us, 0, 0, 0, 0, 0
    )


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


def is_autopilot(msg: Any) -> bool:
    """A HEARTBEAT from a flight controller (not a ground station or another companion)."""
    return msg.autopilot != MAV_AUTOPILOT_INVALID and msg.type not in (
        MAV_TYPE_GCS,
        MAV_TYPE_ONBOARD_CONTROLLER,
    )


@dataclass
class VehicleState:
    """What the link has heard from the one vehicle it serves (times on ``time.monotonic``).

    The autopilot's HEARTBEAT: ``autopilot`` (MAV_AUTOPILOT: 3 ArduPilot, 12 PX4),
    ``custom_mode``, ``base_mode``; ATTITUDE as ``R_ned_frd``; LOCAL_POSITION_NED as
    ``p_ned_m`` and ``v_ned_mps``; HIGHRES_IMU's accelerometer as ``f_frd_mps2`` (the specific
    force in the body's FRD frame: at rest ``-g`` along z); EXTENDED_SYS_STATE's
    ``landed_state`` (its land detector).
    ``system_id`` and ``component_id`` are the autopilot's:
    ``target_system`` if given, else the first autopilot whose HEARTBEAT is heard. Nothing from
    another system or component reaches this state. An ATTITUDE or LOCAL_POSITION_NED that
    ``gate`` refuses (non-finite, implausible, out of order, from before a reboot:
    ``perchpose.io.samples``) is dropped whole (``rejected`` counts them, ``gate.refused``
    by reason): the last good one stays, and ages.
    """

    target_system: int | None = None
    R_ned_frd: Array | None = None
    p_ned_m: Array | None = None
    v_ned_mps: Array | None = None
    f_frd_mps2: Array | None = None
    attitude_t_s: float = float("nan")
    position_t_s: float = float("nan")
    imu_t_s: float = float("nan")
    autopilot: int | None = None
    custom_mode: int = 0
    base_mode: int = 0
    system_id: int | None = None
    component_id: int | None = None
    heartbeat_t_s: float = float("nan")
    heartbeat_period_s: float = math.inf  # between the last two
    landed_state: int = 0
    landed_state_t_s: float = float("nan")
    rejected: int = 0
    gate: SampleGate = field(default_factory=SampleGate)

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)

    def attitude_age_s(self, now: float) -> float:
        """Seconds since the last good ATTITUDE (infinite before the first)."""
        return now - self.attitude_t_s if self.R_ned_frd is not None else math.inf

    def position_age_s(self, now: float) -> float:
        """Seconds since the last good LOCAL_POSITION_NED (infinite before the first)."""
        return now - self.position_t_s if self.p_ned_m is not None else math.inf

    def imu_age_s(self, now: float) -> float:
        """Seconds since the last good HIGHRES_IMU (infinite before the first)."""
        return now - self.imu_t_s if self.f_frd_mps2 is not None else math.inf

    def source(self, msg: Any) -> str:
        """Whose message this is: ``vehicle`` (our autopilot's, locking on to the first
        autopilot heard when no ``target_system`` was given), ``stranger`` (another
        autopilot's) or ``other`` (anything else: not yet locked, another component, a
        ground station)."""
        system, component = msg.get_srcSystem(), msg.get_srcComponent()
        if self.system_id is None:
            if msg.get_type() != "HEARTBEAT" or not is_autopilot(msg):
                return "other"
            if self.target_system is not None and system != self.target_system:
                return "stranger"
            self.system_id, self.component_id = system, component
            return "vehicle"
        if system != self.system_id:
            autopilot = msg.get_type() == "HEARTBEAT" and is_autopilot(msg)
            return "stranger" if autopilot else "other"
        return "vehicle" if component == self.component_id else "other"

    def heard(self, msg: Any, now: float) -> bool:
        """Take in one message from our vehicle (``source`` said so); True if it changed this
        state, False if it was not one of the kinds kept or had a non-finite field."""
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            if not is_autopilot(msg):
                return False
            self.autopilot = int(msg.autopilot)
            self.custom_mode = int(msg.custom_mode)
            self.base_mode = int(msg.base_mode)
            if math.isfinite(self.heartbeat_t_s):
                self.heartbeat_period_s = now - self.heartbeat_t_s
            self.heartbeat_t_s = now
        elif kind == "ATTITUDE":
            t_ms = int(msg.time_boot_ms)
            if self.gate.attitude(t_ms, msg.roll, msg.pitch, msg.yaw, now) is not None:
                self.rejected += 1
                return False
            self.R_ned_frd = R_ned_frd_from_euler(msg.roll, msg.pitch, msg.yaw)
            self.attitude_t_s = now
        elif kind == "LOCAL_POSITION_NED":
            p = np.array([msg.x, msg.y, msg.z], dtype=float)
            v = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
            if self.gate.position(int(msg.time_boot_ms), p, v, now) is not None:
                self.rejected += 1
                return False
            self.p_ned_m, self.v_ned_mps = p, v
            self.position_t_s = now
        elif kind == "HIGHRES_IMU":
            f = np.array([msg.xacc, msg.yacc, msg.zacc], dtype=float)
            if not (np.all(np.isfinite(f)) and np.linalg.norm(f) < MAX_SPECIFIC_FORCE_MPS2):
                self.rejected += 1
                return False
            self.f_frd_mps2 = f
            self.imu_t_s = now
        elif kind == "EXTENDED_SYS_STATE":
            self.landed_state = int(msg.landed_state)
            self.landed_state_t_s = now
        else:
            return False
        return True

    def on_ground(self, now: float, max_age_s: float = 1.0) -> bool | None:
        """What the autopilot's own land detector says (EXTENDED_SYS_STATE's landed state):
        on the ground or not; None when it has said nothing for ``max_age_s``."""
        if not now - self.landed_state_t_s < max_age_s:
            return None
        return self.landed_state == MAV_LANDED_STATE_ON_GROUND


class MavlinkLink:
    """A pymavlink connection to one vehicle, served by a thread of its own.

    url : pymavlink connection string. target_system : the vehicle's MAVLink system id (None:
    the first autopilot heard); messages from other systems are ignored (each stranger said
    once). streams : the vehicle's messages the link asks for (``ATTITUDE``,
    ``LOCAL_POSITION_NED``, ``HIGHRES_IMU``) with MAV_CMD_SET_MESSAGE_INTERVAL at ``stream_hz``
    once it knows the vehicle, again while one does not arrive (3 tries, 2 s apart), then says
    which never came. heartbeat_hz : the rate the link asks of the vehicle's HEARTBEAT, the only
    message that says its flight mode, so that a mode change by its pilot is heard within a
    tenth of a second rather than a second (None: the vehicle's own 1 Hz); ArduPilot honours it,
    PX4 keeps 1 Hz: asked again while it does not come at half that rate (3 tries, 2 s apart),
    then said once. timesync_period_s : how often a TIMESYNC request is sent (0: never; requests
    from the vehicle are answered all the same). report : receives the one-line link reports
    (default: this module's logger).

    No packet ends the link's thread: a message that cannot be packed is dropped, one that
    cannot be used is ignored, and an error in a listener or poller is caught; each kind of
    fault is reported once, in one line, and counted in ``faults``.
    """

    def __init__(
        self,
        url: str,
        *,
        source_system: int = 1,
        source_component: int = MAV_COMP_ID_ONBOARD_COMPUTER,
        heartbeat_period_s: float = 1.0,
        timesync_period_s: float = 1.0,
        retry_period_s: float = 2.0,
        target_system: int | None = None,
        streams: tuple[str, ...] = (),
        stream_hz: float = 50.0,
        heartbeat_hz: float | None = None,
        report: Callable[[str], None] | None = None,
    ) -> None:
        self.url = check_url(url)
        unknown = [name for name in streams if name not in STREAM_IDS]
        if unknown:
            raise LinkError(f"MAVLink streams {unknown}: the link asks only for {list(STREAM_IDS)}")
        if not stream_hz > 0:
            raise LinkError(f"MAVLink stream rate must be positive, got {stream_hz}")
        self.streams = streams
        self.stream_interval_us = round(1e6 / stream_hz)
        self.stream_requests = 0
        self._stream_tries = 0
        self._next_stream_request = 0.0
        if heartbeat_hz is not None and not 1.0 <= heartbeat_hz <= 50.0:
            raise LinkError(f"MAVLink HEARTBEAT rate must be 1 to 50 Hz, got {heartbeat_hz}")
        self.heartbeat_hz = heartbeat_hz
        self.heartbeat_requests = 0
        self._heartbeat_tries = 0
        self._next_heartbeat_request = 0.0
        if target_system is not None and not 1 <= target_system <= 255:
            raise LinkError(f"MAVLink target system {target_system}: expected 1 to 255")
        self.source_system = source_system
        self.source_component = source_component
        self.heartbeat_period_s = heartbeat_period_s
        self.timesync_period_s = timesync_period_s
        self.retry_period_s = retry_period_s
        self.report = report or log.warning
        self.timesync = TimeSync()
        self.vehicle = VehicleState(
            target_system=target_system, gate=SampleGate(on_reboot=self._rebooted)
        )
        self.faults = 0
        self._said: set[str] = set()  # the one-time reports already made
        self.listeners: list[Callable[[Any], None]] = []
        self.pollers: list[Callable[[float], None]] = []
        self.sent = 0
        self.dropped = 0
        self._mavutil = mavutil_module()
        self._lock = threading.Lock()
        self._conn: Any = None
        self._down = False
        self._down_reported = False
        self._next_retry = 0.0
        self._next_heartbeat = 0.0
        self._next_timesync = 0.0
        self._queue: deque[tuple[Send, str]] = deque()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._service, name="mavlink", daemon=True)
        self._thread.start()

    # -- the connection -------------------------------------------------------------------

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

    def _rebooted(self, why: str) -> None:
        """The autopilot rebooted: its clock's offset is measured anew, and its HEARTBEAT's
        rate asked for again."""
        self.timesync.reset()
        self._heartbeat_tries, self._next_heartbeat_request = 0, 0.0
        self.report(f"MAVLink {self.url}: the autopilot rebooted ({why}); TIMESYNC starts over")

    def say_once(self, key: str, line: str) -> None:
        """Report ``line`` the first time ``key`` comes up."""
        if key not in self._said:
            self._said.add(key)
            self.report(line)

    def _fault(self, key: str, line: str) -> None:
        self.faults += 1
        self.say_once(key, f"MAVLink {self.url}: {line} (reported once; the link goes on)")

    def _send(self, send: Send, what: str) -> bool:
        """Send on the service thread; a transport error takes the link down, a message that
        cannot be packed (a field out of its range) is dropped."""
        if self._conn is None:
            return False
        try:
            send(self._conn.mav)
        except OSError as exc:
            self._link_down(f"{self.url} down while sending {what}: {exc}")
            return False
        except Exception as exc:  # pymavlink packs with struct: a bad field raises anything
            self._fault(f"send {what}", f"one {what} could not be sent ({exc}); dropped")
            return False
        return True

    def _drain(self) -> None:
        while True:
            with self._lock:
                if not self._queue:
                    return
                send, what = self._queue.popleft()
            sent = self._send(send, what)
            with self._lock:
                if not sent:  # the link went down with this message in hand
                    self.dropped += 1
                    return
                self.sent += 1

    def _service(self) -> None:
        while True:
            stopping = self._stop.is_set()
            try:
                if self._turn(stopping):
                    break
            except Exception as exc:  # the thread serves the vehicle: it must not die
                self._fault(f"turn {type(exc).__name__}", f"link error {exc!r}")
            for poll in self.pollers:
                try:
                    poll(time.monotonic())
                except Exception as exc:
                    self._fault(f"poll {type(exc).__name__}", f"error while polling: {exc!r}")
            self._wake.wait(0.01)
            self._wake.clear()
        with self._lock:
            self.dropped += len(self._queue)
            self._queue.clear()

    def _turn(self, stopping: bool) -> bool:
        """One turn of the service loop; True when it is time to stop."""
        now = time.monotonic()
        if self._conn is None:
            if stopping:
                return True
            if now >= self._next_retry:
                self._open()
            return False
        self._drain()
        if stopping:
            return True
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + self.heartbeat_period_s
            self._send(self._heartbeat, "HEARTBEAT")
        self._ask_for_streams(now)
        self._ask_for_heartbeats(now)
        if self.timesync_period_s > 0 and now >= self._next_timesync:
            self._next_timesync = now + self.timesync_period_s
            tc1, ts1 = self.timesync.request()
            self._send(partial(_timesync_send, tc1=tc1, ts1=ts1), "TIMESYNC")
        self._receive()
        return False

    def _missing_streams(self, now: float) -> list[str]:
        v = self.vehicle
        ages = {
            "ATTITUDE": v.attitude_age_s(now),
            "LOCAL_POSITION_NED": v.position_age_s(now),
            "HIGHRES_IMU": v.imu_age_s(now),
        }
        return [name for name in self.streams if not ages[name] < STREAM_RETRY_S]

    def _ask_for_streams(self, now: float) -> None:
        """SET_MESSAGE_INTERVAL for each stream asked for that does not arrive, once the
        vehicle is known; said once if they never come."""
        system, component = self.vehicle.system_id, self.vehicle.component_id
        if system is None or component is None or now < self._next_stream_request:
            return
        if not now - self.vehicle.heartbeat_t_s < SILENT_VEHICLE_S:
            return  # the vehicle itself is silent: its streams' rates are not what is wrong
        missing = self._missing_streams(now)
        if not missing:
            return
        if self._stream_tries >= STREAM_TRIES:
            needed = [name for name in missing if name not in OPTIONAL_STREAMS]
            if needed:
                self.say_once(
                    "streams",
                    f"MAVLink {self.url}: the vehicle does not send {' and '.join(needed)} "
                    f"though asked {STREAM_TRIES} times (MAV_CMD_SET_MESSAGE_INTERVAL); set its "
                    "stream rates (ArduPilot SRn_EXTRA1 / SRn_POSITION, PX4 the MAVLink mode)",
                )
            for name in missing:
                if name in OPTIONAL_STREAMS:
                    self.say_once(
                        name,
                        f"MAVLink {self.url}: the vehicle does not send {name} though asked "
                        f"{STREAM_TRIES} times: {OPTIONAL_STREAMS[name]}",
                    )
            return
        self._stream_tries += 1
        self._next_stream_request = now + STREAM_RETRY_S
        for name in missing:
            if self._ask_interval(system, component, STREAM_IDS[name], self.stream_interval_us):
                self.stream_requests += 1

    def _ask_for_heartbeats(self, now: float) -> None:
        """SET_MESSAGE_INTERVAL for the vehicle's HEARTBEAT at ``heartbeat_hz``, again while
        it does not come at half that rate; said once if it never does."""
        system, component = self.vehicle.system_id, self.vehicle.component_id
        if self.heartbeat_hz is None or system is None or component is None:
            return
        # the last HEARTBEAT must be recent: a vehicle falling silent is not asked for a rate
        if now < self._next_heartbeat_request or not now - self.vehicle.heartbeat_t_s < 1.5:
            return
        if self.vehicle.heartbeat_period_s < 2.0 / self.heartbeat_hz:
            self._next_heartbeat_request = math.inf  # it comes at the rate asked
            return
        if self._heartbeat_tries >= STREAM_TRIES:  # asked, and the period stayed long
            self.say_once(
                "heartbeat rate",
                f"MAVLink {self.url}: the vehicle keeps its HEARTBEAT at its own rate though "
                f"asked for {self.heartbeat_hz:g} Hz (PX4 does): a mode change by its pilot is "
                "heard up to a HEARTBEAT period late",
            )
            self._next_heartbeat_request = math.inf
            return
        self._heartbeat_tries += 1
        self._next_heartbeat_request = now + STREAM_RETRY_S
        if self._ask_interval(system, component, HEARTBEAT_ID, round(1e6 / self.heartbeat_hz)):
            self.heartbeat_requests += 1

    def _ask_interval(self, system: int, component: int, message_id: int, interval_us: int) -> bool:
        """MAV_CMD_SET_MESSAGE_INTERVAL for one of the vehicle's messages; False if the link
        could not send it."""
        send = partial(
            _interval_send,
            system=system,
            component=component,
            message_id=message_id,
            interval_us=interval_us,
        )
        return self._send(send, "COMMAND_LONG")

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
                    type=[
                        "HEARTBEAT",
                        "ATTITUDE",
                        "LOCAL_POSITION_NED",
                        "HIGHRES_IMU",
                        "EXTENDED_SYS_STATE",
                        "TIMESYNC",
                    ],
                    blocking=False,
                )
            except OSError as exc:
                self._link_down(f"{self.url} down while reading: {exc}")
                return
            if msg is None:
                return
            try:
                self._take(msg)
            except Exception as exc:  # one bad message is ignored, never the end of the link
                kind = msg.get_type()
                self._fault(f"take {kind}", f"one {kind} could not be used ({exc!r}); ignored")

    def _take(self, msg: Any) -> None:
        source = self.vehicle.source(msg)
        kind = msg.get_type()
        if source == "stranger":
            self.say_once(
                f"stranger {msg.get_srcSystem()}",
                f"MAVLink {self.url}: ignoring autopilot system {msg.get_srcSystem()} "
                f"(serving system {self.vehicle.system_id or self.vehicle.target_system}; "
                "--target-system picks another)",
            )
            return
        if kind == "TIMESYNC":
            # requests are answered whoever asks; only our vehicle's answers set the offset
            if msg.tc1 == 0 or source == "vehicle":
                answer = self.timesync.handle(int(msg.tc1), int(msg.ts1))
                if answer is not None:
                    self._send(partial(_timesync_send, tc1=answer[0], ts1=answer[1]), "TIMESYNC")
            return
        if source != "vehicle":
            return
        if kind == "HEARTBEAT" and math.isnan(self.vehicle.heartbeat_t_s):
            log.info(
                "MAVLink %s: serving autopilot system %s (component %s)",
                self.url,
                self.vehicle.system_id,
                self.vehicle.component_id,
            )
        refused = dict(self.vehicle.gate.refused)
        if self.vehicle.heard(msg, time.monotonic()):
            for listener in self.listeners:
                listener(msg)
            return
        for reason, count in self.vehicle.gate.refused.items():
            if count > refused.get(reason, 0):
                self._fault(f"{reason} {kind}", f"{kind} dropped: {reason}")

    # -- for the senders ------------------------------------------------------------------

    def post(self, send: Send, what: str) -> bool:
        """Queue one message for the link's thread (``send`` gets pymavlink's ``conn.mav``);
        False if the link is down and it is dropped. Never waits on the network."""
        with self._lock:
            if self._down:
                self.dropped += 1
                return False
            if len(self._queue) >= QUEUE_LENGTH:  # a stalled link: the oldest is least useful
                self._queue.popleft()
                self.dropped += 1
            self._queue.append((send, what))
        self._wake.set()
        return True

    def close(self) -> None:
        """Send what is queued, stop the service thread and close the connection."""
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=2.0)
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None
