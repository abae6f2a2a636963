"""The perching phase machine: the controller wrapped in the safety states that fly a vehicle.

``PerchingPilot`` turns each frame's estimate into a world-frame velocity setpoint with the
controller of ``perchpose.control.controller`` and sends it through a ``VehicleCommander`` in
SI units (m/s and rad/s, world z up); each vehicle's adapter converts to its own units and
frames: the Crazyflie link's (``perchpose.io.crazyflie.CflibCommander``: cflib's deg/s), the
MAVLink pilot's (``perchpose.io.mavlink.pilot.SetpointCommander``: NED) and the simulation's
(``perchpose.sim.perch.HeldSetpoint``).

- ``waiting``: nothing is sent until the first usable estimate (the pilot takes over then);
- ``perching``: the controller's setpoints (align, climb, commit);
- ``lost``: the target is gone; the controller hovers, then descends to re-acquire it;
- ``landing``: lost for longer than ``land_after_lost_s``, the controller gave up after its
  tries at a final climb, or stopped by the user: descend at
  ``land_speed_mps`` until the height source says landed (or ``land_duration_s`` elapses), then
  a stop setpoint;
- ``perched``: contact: during the final climb the vehicle's height stopped rising (under
  ``contact_rise_m`` over ``contact_window_s`` while climbing): a stop setpoint cuts the motors
  and the magnet holds the vehicle. Time alone never stops the motors; without a height source
  there is no contact evidence, and a final climb that does not end backs off;
- ``landed``, ``link_lost``, ``released``: nothing more is sent. After a link loss the
  Crazyflie's own commander watchdog levels the vehicle and stops the motors (firmware: 0.5 s
  and 2 s without setpoints); ``released`` is an autopilot taking control back (it left the
  mode that takes our setpoints, or its heartbeat stopped: ``perchpose.io.mavlink.pilot``).

Every setpoint passes ``safe_setpoint`` last: nothing non-finite is sent, and speeds and yaw
rate are clamped to ``PilotSettings.limits``.

The vehicle's own senses are checked too, where the link says how old they are (``ages``):
a non-finite attitude, position or height is never flown on; a sample older than
``PilotSettings.stale_after_s`` stops the climb (a hover setpoint, phase ``hold``, said once)
until it is fresh again; one older than ``senses_lost_after_s`` lands the vehicle (the
Crazyflie) or hands it back to its autopilot (MAVLink), saying why. Contact and "landed" need a
live height: a sample younger than ``live_height_s``, so a height that stopped updating never
reads as "stopped rising".
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray

from perchpose.control.controller import Command, Odometry, PerchingController, Phase, usable
from perchpose.control.setpoint import SetpointLimits, safe_setpoint
from perchpose.errors import ControllerConfigError, require_positive
from perchpose.values import Estimate

Array = NDArray[np.float64]
log = logging.getLogger(__name__)


class PilotState(StrEnum):
    """The pilot's safety states (strings as well, as they appear in files and logs)."""

    WAITING = "waiting"
    PERCHING = "perching"
    LOST = "lost"
    LANDING = "landing"
    PERCHED = "perched"
    LANDED = "landed"
    LINK_LOST = "link_lost"
    RELEASED = "released"


DONE = (PilotState.LANDED, PilotState.PERCHED, PilotState.LINK_LOST, PilotState.RELEASED)
FLYING = (PilotState.PERCHING, PilotState.LOST, PilotState.LANDING)
ON_SENSES_LOST = ("land", "release")


class SenseAges(NamedTuple):
    """How old the vehicle's latest good samples are, in seconds (infinite: none yet)."""

    attitude_s: float
    position_s: float
    height_s: float


class VehicleCommander(Protocol):
    """What the pilot sends a vehicle, in SI units: a velocity in the world frame (z up, m/s)
    with a yaw rate about up (rad/s), or a stop (the motors off: the vehicle is perched or
    landed, and the vehicle's own setpoint priority is handed back)."""

    def send_velocity(
        self, v_world_mps: tuple[float, float, float], yaw_rate_rad_s: float
    ) -> None: ...

    def send_stop(self) -> None: ...


@dataclass(frozen=True)
class PilotSettings:
    """Safety limits (SI units).

    land_after_lost_s : a target lost this long lands the vehicle. land_speed_mps : descent
    speed when landing. land_duration_s : landing ends after this long when no height source
    says so earlier. landed_height_m : height under which the vehicle counts as landed.
    contact_window_s, contact_rise_m : contact is a final climb whose height rose less than
    contact_rise_m over the last contact_window_s. limits : the largest setpoint sent.
    stale_after_s : a vehicle sample (attitude, position, height) older than this stops the
    climb: the pilot hovers until it is fresh. senses_lost_after_s : older than this, the
    pilot lands or releases the vehicle (``on_senses_lost``: ``land`` for the Crazyflie,
    ``release`` for an autopilot, whose own modes then fly it). live_height_s : contact and
    "landed" count only height samples younger than this (a stream at 10 Hz or faster stays
    live between its samples); it must be shorter than the contact window, so that a height
    that froze never makes a contact on its own.
    """

    land_after_lost_s: float = 4.0
    land_speed_mps: float = 0.2
    land_duration_s: float = 10.0
    landed_height_m: float = 0.06
    contact_window_s: float = 0.3
    contact_rise_m: float = 0.005
    setpoint_period_s: float = 0.05
    stale_after_s: float = 0.25
    senses_lost_after_s: float = 1.0
    live_height_s: float = 0.2
    on_senses_lost: str = "land"
    limits: SetpointLimits = field(default_factory=SetpointLimits)

    def __post_init__(self) -> None:
        positive = (
            "land_after_lost_s",
            "land_speed_mps",
            "land_duration_s",
            "contact_window_s",
            "contact_rise_m",
            "setpoint_period_s",
            "stale_after_s",
            "senses_lost_after_s",
            "live_height_s",
        )
        require_positive(self, positive, ControllerConfigError, "pilot setting ")
        if self.on_senses_lost not in ON_SENSES_LOST:
            raise ControllerConfigError(
                f"pilot setting on_senses_lost {self.on_senses_lost!r}: choose "
                f"{' or '.join(ON_SENSES_LOST)}"
            )
        if not self.live_height_s < self.contact_window_s:
            raise ControllerConfigError(
                f"pilot setting live_height_s ({self.live_height_s:g} s) must be below "
                f"contact_window_s ({self.contact_window_s:g} s): a frozen height would read as "
                "contact"
            )
        if not self.stale_after_s < self.senses_lost_after_s:
            raise ControllerConfigError(
                f"pilot setting stale_after_s ({self.stale_after_s:g} s) must be below "
                f"senses_lost_after_s ({self.senses_lost_after_s:g} s)"
            )


@dataclass(frozen=True)
class PilotStep:
    """What the pilot did for one frame: its state and the setpoint sent (None: nothing)."""

    t_s: float
    state: PilotState
    v_mps: tuple[float, float, float] | None
    yaw_rate_rad_s: float | None
    phase: str | None


class ContactDetector:
    """Contact evidence: during the final climb, the height stopped rising."""

    def __init__(self, window_s: float, rise_m: float) -> None:
        self.window_s = window_s
        self.rise_m = rise_m
        self._samples: deque[tuple[float, float]] = deque()

    def reset(self) -> None:
        self._samples.clear()

    def touched(self, t_s: float, height_m: float | None) -> bool:
        """Add a height sample of the final climb; True once the height has risen less than
        ``rise_m`` over a whole window. No live height (None, non-finite) starts the window
        again: contact is never read across a gap."""
        if height_m is None or not math.isfinite(height_m):
            self.reset()
            return False
        self._samples.append((t_s, height_m))
        while len(self._samples) > 1 and t_s - self._samples[1][0] >= self.window_s:
            self._samples.popleft()
        t0, h0 = self._samples[0]
        if t_s - t0 < self.window_s:
            return False
        return max(h for _, h in self._samples) - h0 < self.rise_m


class PerchingPilot:
    """Drives ``commander`` from per-frame estimates; call ``update`` once per camera frame.

    attitude : returns the vehicle's ``R_world_body`` (world z up), e.g. from the Crazyflie's
    state estimate. height_m : the vehicle's height above the ground from its own state
    estimate (None: unknown); it is the contact evidence that ends a perch. odometry : the
    vehicle's position and velocity now (world frame, z up, m and m/s) from its own state
    estimate, or None while unknown; with it the controller rejects disturbances and flies the
    last centimetres on odometry. ages : how old the link's latest attitude, position and
    height samples are (None: always fresh, as in the simulation).
    """

    def __init__(
        self,
        commander: VehicleCommander,
        attitude: Callable[[], Array],
        *,
        controller: PerchingController | None = None,
        settings: PilotSettings | None = None,
        height_m: Callable[[], float | None] | None = None,
        odometry: Callable[[], tuple[Array, Array] | None] | None = None,
        ages: Callable[[], SenseAges] | None = None,
        report: Callable[[str], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.commander = commander
        self.ages = ages
        self._holding = False
        self._bad_attitude_since: float | None = None
        self.clock = clock
        self.attitude = attitude
        self.controller = controller or PerchingController()
        self.settings = settings or PilotSettings()
        self.height_m = height_m
        self.odometry = odometry
        self.report = report or log.warning
        self.state = PilotState.WAITING
        self.transitions: list[tuple[float, PilotState, PilotState]] = []
        self.replaced_setpoints = 0
        self._last_valid_t: float | None = None
        self._landing_since: float | None = None
        self._contact = ContactDetector(
            self.settings.contact_window_s, self.settings.contact_rise_m
        )
        self.last_t_s = 0.0
        # frames and odometry samples may arrive on different threads (a vehicle link's)
        self._lock = threading.RLock()
        self._frame_clock: tuple[float, float] | None = None  # (frame t_s, clock() then)
        if height_m is None:
            self.report(
                "pilot: no height source, so no contact evidence: the motors are never "
                "stopped on the plate, and a final climb backs off after "
                f"{self.controller.settings.commit_timeout_s:g} s"
            )

    # -- state ----------------------------------------------------------------------------

    def _enter(self, state: PilotState, t_s: float, why: str) -> None:
        if state != self.state:
            self.transitions.append((t_s, self.state, state))
            self.report(f"pilot: {self.state} -> {state} at t = {t_s:.2f} s ({why})")
            self.state = state

    @property
    def flying(self) -> bool:
        return self.state in FLYING

    def watch_link(self, crazyflie: Any) -> None:
        """Be told when ``crazyflie`` (a ``cflib.crazyflie.Crazyflie``) loses its link."""
        crazyflie.connection_lost.add_callback(lambda _uri, reason: self.link_lost(str(reason)))

    def link_lost(self, reason: str = "link lost") -> None:
        """The radio link is gone: send nothing more (the firmware's watchdog takes over)."""
        self.release(reason, PilotState.LINK_LOST)

    def release(self, reason: str, state: PilotState = PilotState.RELEASED) -> None:
        """Control is taken back from the pilot (``reason`` says why): send nothing more."""
        with self._lock:
            if self.state not in DONE:
                self._enter(state, self.last_t_s, reason)

    def abort(self, t_s: float, reason: str = "stopped by the user") -> None:
        """Stop perching: land if flying; otherwise never take over."""
        with self._lock:
            if self.flying and self.state != PilotState.LANDING:
                self._start_landing(t_s, reason)
            elif self.state == PilotState.WAITING:
                self._enter(PilotState.LANDED, t_s, reason)

    # -- setpoints ------------------------------------------------------------------------

    def _send(self, t_s: float, v: Array, yaw_rate_rad_s: float, phase: str | None) -> PilotStep:
        sp = safe_setpoint(v, yaw_rate_rad_s, self.settings.limits)
        if sp.replaced:
            self.replaced_setpoints += 1
            if self.replaced_setpoints == 1:
                self.report(
                    f"pilot: a non-finite setpoint at t = {t_s:.2f} s was replaced by a hover "
                    "(reported once)"
                )
        self.commander.send_velocity(sp.v_mps, sp.yaw_rate_rad_s)
        return PilotStep(t_s, self.state, sp.v_mps, sp.yaw_rate_rad_s, phase)

    def _stop(self, t_s: float, state: PilotState, why: str) -> PilotStep:
        self._enter(state, t_s, why)  # first: a commander may ask which stop this is
        self.commander.send_stop()
        return PilotStep(t_s, self.state, None, None, None)

    def _start_landing(self, t_s: float, why: str) -> None:
        self._landing_since = t_s
        self._enter(PilotState.LANDING, t_s, why)

    # -- the vehicle's senses -------------------------------------------------------------

    def _height(self) -> float | None:
        """The vehicle's height if live (young enough and finite), else None."""
        if self.height_m is None:
            return None
        if self.ages is not None and not self.ages().height_s < self.settings.live_height_s:
            return None
        height = self.height_m()
        return height if height is not None and math.isfinite(height) else None

    def _motion(self) -> tuple[Array, Array] | None:
        """The vehicle's position and velocity, None if unknown or not finite."""
        motion = self.odometry() if self.odometry is not None else None
        if motion is None or not (
            np.all(np.isfinite(motion[0])) and np.all(np.isfinite(motion[1]))
        ):
            return None
        return motion

    def _age(self, sense: str) -> float:
        """How old the vehicle's latest ``attitude`` or ``position`` sample is (0 without
        ``ages``): the controller keeps each sample at the time it describes."""
        if self.ages is None:
            return 0.0
        ages = self.ages()
        age = ages.attitude_s if sense == "attitude" else ages.position_s
        return age if math.isfinite(age) and age >= 0.0 else 0.0

    def _stale(self, t_s: float) -> tuple[str, float] | None:
        """The oldest of the samples the pilot flies on, if it is older than
        ``stale_after_s``. A non-finite attitude is stale at once, and ages from the first
        frame that had one."""
        if not np.all(np.isfinite(self.attitude())):
            if self._bad_attitude_since is None:
                self._bad_attitude_since = t_s
            return "attitude", self.settings.stale_after_s + t_s - self._bad_attitude_since
        self._bad_attitude_since = None
        if self.ages is None:
            return None
        ages = self.ages()
        named = [("attitude", ages.attitude_s)]
        if self.odometry is not None:
            named.append(("position", ages.position_s))
        if self.height_m is not None:
            named.append(("height", ages.height_s))
        name, age = max(named, key=lambda item: item[1])
        return None if age < self.settings.stale_after_s else (name, age)

    def _hold(self, t_s: float, name: str, age_s: float) -> PilotStep:
        """A stale sense: hover (no climb) until it is fresh; land or release once lost."""
        s = self.settings
        self._contact.reset()
        if age_s >= s.senses_lost_after_s:
            old = (
                f"no {name} from the vehicle"
                if math.isinf(age_s)
                else (f"the vehicle's {name} is {age_s:.1f} s old")
            )
            if s.on_senses_lost == "release":
                self._enter(PilotState.RELEASED, t_s, f"{old}: its autopilot flies it now")
                return PilotStep(t_s, self.state, None, None, None)
            self._start_landing(t_s, old)
            return self._land_step(t_s)
        if not self._holding:
            self.report(
                f"pilot: the vehicle's {name} is {age_s:.2f} s old at t = {t_s:.2f} s: hovering, "
                f"no climb, until it is fresh ({s.on_senses_lost} after "
                f"{s.senses_lost_after_s:g} s)"
            )
            self._holding = True
        return self._send(t_s, np.zeros(3), 0.0, "hold")

    def _land_step(self, t_s: float) -> PilotStep:
        s = self.settings
        since = self._landing_since if self._landing_since is not None else t_s
        height = self._height()
        if (height is not None and height < s.landed_height_m) or t_s - since >= (
            s.land_duration_s
        ):
            return self._stop(t_s, PilotState.LANDED, "on the ground")
        return self._send(t_s, np.array([0.0, 0.0, -s.land_speed_mps]), 0.0, None)

    def update(self, estimate: Estimate | None, t_s: float) -> PilotStep:
        """One frame: the estimate (None, not valid or too old: no target) at time ``t_s``.
        An estimate of a live frame (``grabbed_s`` known, on this pilot's ``clock``) moves the
        pilot's time on to its capture time plus the time since its grab, so its latency is
        counted and the controller places it at its capture time."""
        with self._lock:
            return self._update(estimate, t_s)

    def tick_now(self) -> PilotStep | None:
        """``tick`` at the present moment on the frames' clock (the last frame's ``t_s`` plus
        the time since it was handed over): what a vehicle link calls on each state-estimate
        sample it receives."""
        with self._lock:
            if self._frame_clock is None:
                return None
            t_frame, then = self._frame_clock
            return self.tick(t_frame + max(0.0, self.clock() - then))

    def tick(self, t_s: float) -> PilotStep | None:
        """Between camera frames, on a new odometry sample at ``t_s`` (the frames' clock):
        while perching, a setpoint from the controller's odometry loop
        (``PerchingController.between_frames``) and the contact check; None when nothing was
        sent (not perching, no odometry, nothing held to steer on)."""
        with self._lock:
            if self.state != PilotState.PERCHING or self.odometry is None or t_s < self.last_t_s:
                return None
            motion = self._motion()
            if motion is None or self._stale(t_s) is not None:
                return None
            odometry = Odometry(t_s - self._age("position"), motion[0], motion[1])
            command = self.controller.between_frames(
                t_s, self.attitude(), odometry, self._age("attitude")
            )
            if command is None:
                return None
            self.last_t_s = t_s
            if command.phase == Phase.COMMIT and self._contact.touched(t_s, self._height()):
                return self._stop(
                    t_s, PilotState.PERCHED, "the final climb stopped against the plate"
                )
            return self._send(t_s, command.v_mps, command.yaw_rate_rad_s, command.phase)

    def _update(self, estimate: Estimate | None, t_s: float) -> PilotStep:
        if estimate is not None and math.isfinite(estimate.grabbed_s):
            # a live frame: now is its capture time plus the time since it was grabbed (the
            # estimate's latency), not the frame's own time, on the frames' clock
            t_s = max(t_s, estimate.t_s + max(0.0, self.clock() - estimate.grabbed_s))
        self.last_t_s = t_s
        self._frame_clock = (t_s, self.clock())
        limit_s = self.controller.settings.max_estimate_age_s
        fresh = usable(estimate, t_s, limit_s)
        if self.state == PilotState.WAITING:
            if not fresh:
                return PilotStep(t_s, self.state, None, None, None)
            self._enter(PilotState.PERCHING, t_s, "target in view")
        if self.state in DONE:
            return PilotStep(t_s, self.state, None, None, None)
        if self.state == PilotState.LANDING:
            return self._land_step(t_s)
        if fresh:
            self._last_valid_t = t_s
        stale = self._stale(t_s)
        if stale is not None:
            return self._hold(t_s, *stale)
        if self._holding:
            self.report(f"pilot: the vehicle's samples are fresh again at t = {t_s:.2f} s")
            self._holding = False
        motion = self._motion()
        odometry = None if motion is None else Odometry(t_s - self._age("position"), *motion)
        command: Command = self.controller.update(
            estimate, t_s, self.attitude(), odometry, self._age("attitude")
        )
        return self._follow(command, t_s)

    def _follow(self, command: Command, t_s: float) -> PilotStep:
        """The state the controller's command leads to, and the setpoint sent in it."""
        s = self.settings
        if command.phase == Phase.GIVE_UP:
            tries = self.controller.tries
            self._start_landing(t_s, f"gave up after {tries} final climbs without contact")
            return self._land_step(t_s)
        if command.phase == Phase.COMMIT:
            if self._contact.touched(t_s, self._height()):
                return self._stop(
                    t_s, PilotState.PERCHED, "the final climb stopped against the plate"
                )
            self._enter(PilotState.PERCHING, t_s, "final climb")
        else:
            self._contact.reset()
            if command.phase == Phase.LOST:
                last = self._last_valid_t if self._last_valid_t is not None else t_s
                if t_s - last >= s.land_after_lost_s:
                    self._start_landing(t_s, f"target lost for {t_s - last:.1f} s")
                    return self._land_step(t_s)
                self._enter(PilotState.LOST, t_s, "target lost")
            else:
                self._enter(PilotState.PERCHING, t_s, "target in view")
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
        while self.state == PilotState.LANDING:
            with self._lock:
                self._land_step(clock() - t0)
            sleep(self.settings.setpoint_period_s)
