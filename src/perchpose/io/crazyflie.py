"""Flying a Crazyflie onto the target with the perching controller, through cflib's commander.

``PerchingPilot`` turns each frame's estimate into a world-frame velocity setpoint
(``Commander.send_velocity_world_setpoint``: m/s and deg/s, world z up) with the controller of
``perchpose.control`` and wraps it in a safety state machine:

- ``waiting``: nothing is sent until the first valid estimate (the pilot takes over then);
- ``perching``: the controller's setpoints (align, climb, commit);
- ``lost``: the target is gone; the controller hovers, then descends to re-acquire it;
- ``landing``: lost for longer than ``land_after_lost_s``, or stopped by the user: descend at
  ``land_speed_mps`` until the height source says landed (or ``land_duration_s`` elapses), then
  a stop setpoint;
- ``perched``: the commit climb has run ``perched_after_commit_s`` (the camera is then too close
  to see anything): a stop setpoint cuts the motors and the magnet holds the vehicle;
- ``landed``, ``link_lost``: nothing more is sent. After a link loss the Crazyflie's own
  commander watchdog levels the vehicle and stops the motors (firmware: 0.5 s and 2 s without
  setpoints).

Only ``connect`` imports cflib; ``PerchingPilot`` works with any object that has cflib's
``commander`` (tests use a real ``cflib.crazyflie.Crazyflie`` over a fake link).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from perchpose.control import Command, PerchingController
from perchpose.errors import LinkError, require_positive
from perchpose.estimator import Estimate

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

STATES = ("waiting", "perching", "lost", "landing", "perched", "landed", "link_lost")
FLYING = ("perching", "lost", "landing")


class CommanderLike(Protocol):
    """The part of ``cflib.crazyflie.commander.Commander`` the pilot uses."""

    def send_velocity_world_setpoint(
        self, vx: float, vy: float, vz: float, yawrate: float
    ) -> None: ...

    def send_stop_setpoint(self) -> None: ...

    def send_notify_setpoint_stop(self, remain_valid_milliseconds: int = 0) -> None: ...


@dataclass(frozen=True)
class PilotSettings:
    """Safety limits (SI units).

    land_after_lost_s : a target lost this long lands the vehicle. land_speed_mps : descent
    speed when landing. land_duration_s : landing ends after this long when no height source
    says so earlier. landed_height_m : height under which the vehicle counts as landed.
    perched_after_commit_s : time in the final climb after which the vehicle is taken to be on
    the plate and the motors are stopped.
    """

    land_after_lost_s: float = 4.0
    land_speed_mps: float = 0.2
    land_duration_s: float = 10.0
    landed_height_m: float = 0.06
    perched_after_commit_s: float = 1.5
    setpoint_period_s: float = 0.05

    def __post_init__(self) -> None:
        positive = (
            "land_after_lost_s",
            "land_speed_mps",
            "land_duration_s",
            "perched_after_commit_s",
            "setpoint_period_s",
        )
        require_positive(self, positive, LinkError, "pilot setting ")


@dataclass(frozen=True)
class PilotStep:
    """What the pilot did for one frame: its state and the setpoint sent (None: nothing)."""

    t_s: float
    state: str
    v_mps: tuple[float, float, float] | None
    yaw_rate_deg_s: float | None
    phase: str | None


class PerchingPilot:
    """Drives ``commander`` from per-frame estimates; call ``update`` once per camera frame.

    attitude : returns the vehicle's ``R_world_body`` (world z up), e.g. from the Crazyflie's
    state estimate. height_m : optional, the vehicle's height above the ground (None: unknown).
    """

    def __init__(
        self,
        commander: CommanderLike,
        attitude: Callable[[], Array],
        *,
        controller: PerchingController | None = None,
        settings: PilotSettings | None = None,
        height_m: Callable[[], float | None] | None = None,
        report: Callable[[str], None] | None = None,
    ) -> None:
        self.commander = commander
        self.attitude = attitude
        self.controller = controller or PerchingController()
        self.settings = settings or PilotSettings()
        self.height_m = height_m
        self.report = report or log.warning
        self.state = "waiting"
        self.transitions: list[tuple[float, str, str]] = []
        self._last_valid_t: float | None = None
        self._commit_since: float | None = None
        self._landing_since: float | None = None
        self.last_t_s = 0.0

    # -- state ----------------------------------------------------------------------------

    def _enter(self, state: str, t_s: float, why: str) -> None:
        if state != self.state:
            self.transitions.append((t_s, self.state, state))
            self.report(f"crazyflie: {self.state} -> {state} at t = {t_s:.2f} s ({why})")
            self.state = state

    @property
    def flying(self) -> bool:
        return self.state in FLYING

    def watch_link(self, crazyflie: Any) -> None:
        """Be told when ``crazyflie`` (a ``cflib.crazyflie.Crazyflie``) loses its link."""
        crazyflie.connection_lost.add_callback(lambda _uri, reason: self.link_lost(str(reason)))

    def link_lost(self, reason: str = "link lost") -> None:
        """The radio link is gone: send nothing more (the firmware's watchdog takes over)."""
        if self.state not in ("landed", "perched", "link_lost"):
            self._enter("link_lost", self.last_t_s, reason)

    def abort(self, t_s: float, reason: str = "stopped by the user") -> None:
        """Stop perching: land if flying; otherwise never take over."""
        if self.flying and self.state != "landing":
            self._start_landing(t_s, reason)
        elif self.state == "waiting":
            self._enter("landed", t_s, reason)

    # -- setpoints ------------------------------------------------------------------------

    def _send(self, t_s: float, v: Array, yaw_rate_rad_s: float, phase: str | None) -> PilotStep:
        yaw_rate_deg_s = math.degrees(yaw_rate_rad_s)
        self.commander.send_velocity_world_setpoint(
            float(v[0]), float(v[1]), float(v[2]), yaw_rate_deg_s
        )
        vx, vy, vz = (float(c) for c in v)
        return PilotStep(t_s, self.state, (vx, vy, vz), yaw_rate_deg_s, phase)

    def _stop(self, t_s: float, state: str, why: str) -> PilotStep:
        self.commander.send_stop_setpoint()
        self.commander.send_notify_setpoint_stop(0)
        self._enter(state, t_s, why)
        return PilotStep(t_s, self.state, None, None, None)

    def _start_landing(self, t_s: float, why: str) -> None:
        self._landing_since = t_s
        self._enter("landing", t_s, why)

    def _land_step(self, t_s: float) -> PilotStep:
        s = self.settings
        since = self._landing_since if self._landing_since is not None else t_s
        height = self.height_m() if self.height_m is not None else None
        if (height is not None and height < s.landed_height_m) or t_s - since >= (
            s.land_duration_s
        ):
            return self._stop(t_s, "landed", "on the ground")
        return self._send(t_s, np.array([0.0, 0.0, -s.land_speed_mps]), 0.0, None)

    def update(self, estimate: Estimate | None, t_s: float) -> PilotStep:
        """One frame: the estimate (None or not valid: no target) at time ``t_s``."""
        self.last_t_s = t_s
        s = self.settings
        valid = estimate is not None and estimate.valid
        if self.state == "waiting":
            if not valid:
                return PilotStep(t_s, self.state, None, None, None)
            self._enter("perching", t_s, "target in view")
        if self.state in ("landed", "perched", "link_lost"):
            return PilotStep(t_s, self.state, None, None, None)
        if self.state == "landing":
            return self._land_step(t_s)
        if valid:
            self._last_valid_t = t_s
        command: Command = self.controller.update(estimate, t_s, self.attitude())
        if command.phase == "commit":
            if self._commit_since is None:
                self._commit_since = t_s
            if t_s - self._commit_since >= s.perched_after_commit_s:
                return self._stop(t_s, "perched", "final climb done")
            self._enter("perching", t_s, "final climb")
        elif command.phase == "lost":
            last = self._last_valid_t if self._last_valid_t is not None else t_s
            if t_s - last >= s.land_after_lost_s:
                self._start_landing(t_s, f"target lost for {t_s - last:.1f} s")
                return self._land_step(t_s)
            self._enter("lost", t_s, "target lost")
        else:
            self._enter("perching", t_s, "target in view")
        return self._send(t_s, command.v_mps, command.yaw_rate_rad_s, command.phase)

    def __call__(self, estimate: Estimate | None, t_s: float) -> None:
        """The per-frame hook ``track`` calls."""
        self.update(estimate, t_s)

    def land(
        self,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        """Finish a landing in real time (after ``abort`` or a lost target), sending a setpoint
        every ``setpoint_period_s`` until landed."""
        t0 = clock() - self.last_t_s
        while self.state == "landing":
            self._land_step(clock() - t0)
            sleep(self.settings.setpoint_period_s)


def R_world_body_from_quaternion(qw: float, qx: float, qy: float, qz: float) -> Array:
    """Rotation matrix of a unit quaternion (body to world)."""
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz) or 1.0
    w, x, y, z = qw / n, qx / n, qy / n, qz / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


class CrazyflieConnection:
    """An open cflib link with the vehicle's attitude and height streamed from its state
    estimate (``stateEstimate.qw/qx/qy/qz`` and ``stateEstimate.z``, 50 Hz)."""

    def __init__(self, uri: str, report: Callable[[str], None] | None = None) -> None:
        try:
            import cflib.crtp
            from cflib.crazyflie import Crazyflie
            from cflib.crazyflie.log import LogConfig
            from cflib.crazyflie.syncCrazyflie import SyncCrazyflie
        except ImportError as exc:
            raise LinkError(
                "the Crazyflie link needs cflib: pip install 'perchpose[crazyflie]'"
            ) from exc
        self.uri = uri
        self.report = report or log.warning
        self._R_world_body = np.eye(3)
        self._height_m: float | None = None
        cflib.crtp.init_drivers()
        self.cf: Any = Crazyflie()
        self._sync = SyncCrazyflie(uri, cf=self.cf)
        try:
            self._sync.open_link()
        except Exception as exc:  # cflib raises bare Exceptions for a missing radio or bad URI
            first_line = (str(exc).strip().splitlines() or ["no reason given"])[0]
            raise LinkError(f"cannot open Crazyflie link {uri}: {first_line}") from exc
        names = ["stateEstimate.qw", "stateEstimate.qx", "stateEstimate.qy", "stateEstimate.qz"]
        self._log = LogConfig(name="perchpose", period_in_ms=20)
        for name in [*names, "stateEstimate.z"]:
            self._log.add_variable(name, "float")
        self._log.data_received_cb.add_callback(self._state)
        try:
            self.cf.log.add_config(self._log)
            self._log.start()
        except (KeyError, AttributeError) as exc:
            self._sync.close_link()
            raise LinkError(f"{uri}: the firmware does not log the state estimate: {exc}") from exc

    def _state(self, _timestamp: int, data: dict[str, float], _config: object) -> None:
        self._R_world_body = R_world_body_from_quaternion(
            data["stateEstimate.qw"],
            data["stateEstimate.qx"],
            data["stateEstimate.qy"],
            data["stateEstimate.qz"],
        )
        self._height_m = float(data["stateEstimate.z"])

    def attitude(self) -> Array:
        return self._R_world_body

    def height_m(self) -> float | None:
        return self._height_m

    def pilot(self, **kwargs: Any) -> PerchingPilot:
        """A pilot on this link, told about a link loss."""
        pilot = PerchingPilot(
            self.cf.commander, self.attitude, height_m=self.height_m, report=self.report, **kwargs
        )
        pilot.watch_link(self.cf)
        return pilot

    def close(self) -> None:
        try:
            self._log.stop()
        finally:
            self._sync.close_link()


def connect(uri: str, report: Callable[[str], None] | None = None) -> CrazyflieConnection:
    """Open ``uri`` (e.g. ``radio://0/80/2M/E7E7E7E7E7``) and stream the vehicle's state."""
    if not uri.startswith(("radio://", "usb://", "udp://", "tcp://", "debug://")):
        raise LinkError(f"Crazyflie URI {uri!r}: expected e.g. radio://0/80/2M/E7E7E7E7E7")
    return CrazyflieConnection(uri, report)
