"""The perching phase machine: the controller wrapped in the safety states that fly a vehicle.

``PerchingPilot`` turns each frame's estimate into a world-frame velocity setpoint with the
controller of ``perchpose.control.controller`` and sends it through a ``VehicleCommander`` in
SI units (m/s and rad/s, world z up); each vehicle's adapter converts to its own units and
frames: the Crazyflie link's (``perchpose.io.crazyflie.CflibCommander``: cflib's deg/s), the
MAVLink pilot's (``perchpose.io.mavlink.pilot.SetpointCommander``: NED) and the simulation's
(``perchpose.sim.perch.HeldSetpoint``).

The pilot runs on its own clock, not on frames: ``update`` hands it a frame, ``tick`` moves it
on (at least every ``setpoint_period_s`` from ``perchpose.control.pilot_clock.PilotClock`` on a
vehicle link, on each odometry sample, and between frames in the simulation). Every tick reads
the watchdogs, so a camera that stalls, senses that stop and a landing all go on without frames.

- ``waiting``: nothing is sent until the first usable estimate (the pilot takes over then);
- ``perching``: the controller's setpoints (align, climb, commit); between frames, the
  controller's odometry loop;
- ``lost``: the target is gone (or no frame came for ``frame_timeout_s``: the camera's
  watchdog): the controller holds on odometry, hovers, then descends to re-acquire it;
- ``landing``: lost for longer than ``land_after_lost_s``, the controller gave up after its
  tries at a final climb, the vehicle's senses were lost, or stopped by the user: descend at
  ``land_speed_mps`` until touchdown is sensed (``perchpose.control.evidence``: a live height
  near the ground that stopped moving, the vertical speed near zero), then a stop setpoint.
  Time never ends a landing: a vehicle that does not come down keeps its motors and is said
  again every ``stuck_report_s``. Without a live height an autopilot is handed its own LAND
  (``VehicleCommander.send_land``); a vehicle without one (the Crazyflie) keeps descending at
  the landing speed until a live height senses the touchdown, and the pilot says so;
- ``perched``: contact: during the final climb (or a climb at its speed with the plate
  within ``climb_contact_within_m``) the vehicle's height stopped rising (under
  ``contact_rise_m`` over ``contact_window_s`` while climbing), or in any phase with the
  plate within ``held_within_m`` by the camera's last measured frame (its own distance, not
  the odometry's) or the height within ``held_height_m`` of the plate's by those frames, its
  height held still (within ``held_still_m`` over ``held_window_s``) against vertical speeds
  asked that would have moved it twice that, and still the plate's height by those frames
  (the magnet caught it), and, where the link gives the accelerometer, rigid
  (``rigid_spread_mps2`` over ``rigid_window_s``), and, without the camera's word on the plate
  within the last two ``caught_window_s``, level (``held_level_deg``). Contact evidence
  alone does not stop the motors: the pilot first tries the magnet's hold
  (``control.seat_check``: a level thrust under the hover's, ``seat_check_thrust``, where the
  link takes one, else a descent at ``seat_check_mps``, for ``seat_check_s``). A vehicle whose
  accelerometer read no fall (``seat_fall_mps2``) and whose height stayed within
  ``seat_drop_m`` is held: a stop setpoint cuts the motors. One that came down is not (its
  gear against the plate beyond the magnet's hold, or beside the plate): the pilot says so
  and the controller backs off for another final climb (or gives up: landing). Time alone
  never stops the motors; without a height source there is no contact evidence, and a final
  climb that does not end backs off;
- ``landed``, ``link_lost``, ``released``: nothing more is sent. After a link loss the
  Crazyflie's own commander watchdog levels the vehicle and stops the motors (firmware: 0.5 s
  and 2 s without setpoints); ``released`` is an autopilot taking control back (it left the
  mode that takes our setpoints, or its heartbeat stopped: ``perchpose.io.mavlink.pilot``).

Every setpoint passes ``safe_setpoint`` last: nothing non-finite is sent, and speeds and yaw
rate are clamped to ``PilotSettings.limits``.

The vehicle's own senses are checked on every frame and every tick, in every flying state,
where the link says how old they are (``ages``): a non-finite attitude, position or height is
never flown on; a sample older than ``PilotSettings.stale_after_s`` stops the climb (a hover
setpoint, phase ``hold``, said once) until it is fresh again; one older than
``senses_lost_after_s`` lands the vehicle (the Crazyflie) or hands it back to its autopilot
(MAVLink; while landing, to its LAND), saying why. Contact and touchdown need a live height: a
sample younger than ``live_height_s``, so a height that stopped updating never reads as
"stopped rising" or "on the ground"; a landing goes on descending through a shorter gap
(touchdown unsensed until the height is live again).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from perchpose.control.attitude_command import LeanLoop
from perchpose.control.controller import (
    Command,
    Odometry,
    PerchingController,
    Phase,
    carried,
    usable,
)
from perchpose.control.evidence import (
    ContactDetector,
    HeldDetector,
    RigidDetector,
    TouchdownDetector,
    line_at,
)
from perchpose.control.gyro import BlendedAttitude, GyroReading
from perchpose.control.history import newest_at
from perchpose.control.lean import GRAVITY_MPS2, LeanCorrection
from perchpose.control.lean_follow import LeanFollowWatch
from perchpose.control.pilot_settings import ON_SENSES_LOST, PilotSettings
from perchpose.control.seat_check import FALLING_READINGS, SeatCheck, SeatChecks, SeatVerdict
from perchpose.control.setpoint import Setpoint, safe_setpoint
from perchpose.geometry import lean_deg, leaned, roll_pitch_rad, yaw_rad
from perchpose.values import Estimate

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

__all__ = [
    "DONE",
    "FLYING",
    "ON_SENSES_LOST",
    "PerchingPilot",
    "PilotSettings",
    "PilotState",
    "PilotStep",
    "SenseAges",
    "VehicleCommander",
]


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
# the camera's measured words on the plate's height averaged for the held-contact evidence
PLATE_WORDS = 15  # half a second of frames at 30 fps
HEIGHT_HISTORY = 128  # live heights kept, to pair a frame with the height at its capture
HEIGHT_FIT_S = 0.15  # the heights either side of a capture the height there is fitted to


class SenseAges(NamedTuple):
    """How old the vehicle's latest good samples are, in seconds (infinite: none yet)."""

    attitude_s: float
    position_s: float
    height_s: float


class VehicleCommander(Protocol):
    """What the pilot sends a vehicle, in SI units: a velocity in the world frame (z up, m/s)
    with a yaw rate about up (rad/s), a stop (the motors off: the vehicle is perched or
    landed, and the vehicle's own setpoint priority is handed back), or the vehicle's own
    landing where it has one."""

    def send_velocity(
        self, v_world_mps: tuple[float, float, float], yaw_rate_rad_s: float
    ) -> None: ...

    def send_stop(self) -> None: ...

    def send_land(self) -> bool:
        """Hand the landing to the vehicle's own (an autopilot's LAND); False where the
        vehicle has none (the pilot then lands it itself)."""
        ...


@runtime_checkable
class VelocityGainSetter(Protocol):
    """A commander that can set the vehicle's horizontal velocity-loop gain (a parameter of
    its flight controller) and give the vehicle's own back."""

    def set_velocity_gain(self, gain_per_s: float) -> bool:
        """Set the gain (1/s); False where the vehicle refused or cannot (nothing changed)."""
        ...

    def restore_velocity_gain(self) -> None:
        """Give back the gain the vehicle had before (nothing where none was set)."""
        ...


@runtime_checkable
class FullStateSender(Protocol):
    """A commander that sends full-state setpoints (``PilotSettings.command``): a position
    (world frame of the vehicle's odometry, m), a velocity (m/s), a yaw (rad) and a yaw rate
    (rad/s), which the vehicle's own position loop holds."""

    def send_full_state(
        self,
        p_world_m: tuple[float, float, float],
        v_world_mps: tuple[float, float, float],
        yaw_rad: float,
        yaw_rate_rad_s: float,
    ) -> None: ...


@runtime_checkable
class AttitudeSender(Protocol):
    """A commander that sends attitude setpoints (``PilotSettings.command``): a roll and a
    pitch (rad, ZYX Euler angles under the vehicle's heading: pitch positive nose down, roll
    positive right side down), a yaw rate (rad/s, counter-clockwise) and a height (world z of
    the vehicle's own estimate, m), which its attitude and height loops hold."""

    def send_attitude(
        self, roll_rad: float, pitch_rad: float, yaw_rate_rad_s: float, z_m: float
    ) -> None: ...


@runtime_checkable
class ThrustSender(Protocol):
    """A commander that sends a level attitude with a collective thrust, as a fraction of the
    thrust its vehicle hovers on, and no height loop: what tries the magnet's hold
    (``control.seat_check``)."""

    def send_level_thrust(self, hover_fraction: float) -> None: ...


@runtime_checkable
class PositionFixSender(Protocol):
    """A commander that hands the vehicle's own state estimator an external position (world
    frame of its odometry, m), as a motion-capture system does."""

    def send_position_fix(self, p_world_m: tuple[float, float, float]) -> bool:
        """Send it; False where the vehicle takes none (nothing was sent)."""
        ...


@dataclass(frozen=True)
class PilotStep:
    """What the pilot did for one frame or tick: its state and the setpoint sent (None: nothing)."""

    t_s: float
    state: PilotState
    v_mps: tuple[float, float, float] | None
    yaw_rate_rad_s: float | None
    phase: str | None


def _lean_loop(
    settings: PilotSettings, controller: PerchingController, commander: VehicleCommander
) -> tuple[LeanLoop, LeanFollowWatch]:
    """The pilot's horizontal velocity loop for attitude setpoints, cancelling the push as the
    controller would, and the watch on whether the vehicle flies the leans it sends; a
    controller flown so (a link that takes them) is told (``use_lean_command``)."""
    c = controller.settings
    if settings.command == "attitude" and isinstance(commander, AttitudeSender):
        controller.use_lean_command()
    loop = LeanLoop(
        settings.lean_gain_per_s,
        math.radians(settings.max_lean_deg),
        push_feedforward=c.push_feedforward,
        push_filter_s=c.push_filter_s,
        max_push_mps2=c.max_push_mps2,
        lead_s=settings.lean_lead_s,
    )
    watch = LeanFollowWatch(
        settings.lean_response_s, settings.lean_follow_window_s, settings.lean_follow_error_deg
    )
    return loop, watch


class PerchingPilot:
    """Drives ``commander`` from per-frame estimates (``update``) and its own clock (``tick``).

    attitude : returns the vehicle's ``R_world_body`` (world z up), e.g. from the Crazyflie's
    state estimate. height_m : the vehicle's height above the ground from its own state
    estimate (None: unknown); it is the contact and touchdown evidence. odometry : the
    vehicle's position and velocity now (world frame, z up, m and m/s) from its own state
    estimate, or None while unknown; with it the controller rejects disturbances and flies the
    last centimetres on odometry. ages : how old the link's latest attitude, position and
    height samples are (None: always fresh, as in the simulation). clock : the monotonic clock
    that ``tick_now`` and live frames' ``captured_s`` are on. on_ground : the vehicle's own
    land detector where it has one (an autopilot's EXTENDED_SYS_STATE: True on the ground,
    None when it says nothing); while landing, its word is a touchdown too. specific_force :
    the vehicle's accelerometer along body x and y (and z, unused), m/s^2: its latest sample,
    as old as the odometry's; None while unknown. It is the aerodynamic push, which the
    controller cancels as it comes (``ControllerSettings.push_feedforward``). gyro : the
    vehicle's gyro integrated where its samples arrive (``control.gyro.GyroAttitude``), as
    old as the attitude's; with a drag-free estimate (``PilotSettings.lean_lag_s``) the
    attitude the pilot uses follows it over ``PilotSettings.gyro_blend_s``, and the
    controller's inertial filter takes the odometry's error as correlated from the start
    (``InertialTracker.assume_correlated``).
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
        on_ground: Callable[[], bool | None] | None = None,
        specific_force: Callable[[], Array | None] | None = None,
        gyro: Callable[[], GyroReading | None] | None = None,
    ) -> None:
        self.commander = commander
        self.gyro = gyro
        self.specific_force = specific_force
        self.on_ground = on_ground
        self.ages = ages
        self._holding = False
        self._bad_attitude_since: float | None = None
        self.clock = clock
        self.attitude = attitude
        self.controller = controller or PerchingController()
        self.settings = settings or PilotSettings()
        lag_s = self.settings.lean_lag_s
        self.lean = LeanCorrection(lag_s) if lag_s > 0 else None
        self.blend = BlendedAttitude(self.settings.gyro_blend_s) if lag_s > 0 else None
        if lag_s > 0:  # a Kalman filter's velocity: its error is correlated however small
            self.controller.inertial.assume_correlated()
        self._lean_loop, self._lean_watch = _lean_loop(self.settings, self.controller, commander)
        self.height_m, self.odometry = height_m, odometry
        self.report = report or log.warning
        self.state = PilotState.WAITING
        self._gain_raised = False
        self._fixes_taken = True  # until the commander says its vehicle takes none
        self._velocity_only_said = False
        self.transitions: list[tuple[float, PilotState, PilotState]] = []
        # non-finite setpoints replaced by a hover; times the camera's watchdog fired
        self.replaced_setpoints = self.silences = 0
        self._last_valid_t: float | None = None
        self._frame_t: float | None = None  # the pilot's time of the last frame handed over
        self._camera_silent = False
        self._landing_since: float | None = None
        self._landing_said: tuple[float, str] | None = None  # (when, which news) last said
        s = self.settings
        self._contact = ContactDetector(s.contact_window_s, s.contact_rise_m)
        self._held = HeldDetector(s.held_window_s, s.held_still_m)
        self._caught_held = HeldDetector(s.caught_window_s, s.held_still_m)
        self._rigid = RigidDetector(s.rigid_window_s, s.rigid_spread_mps2)
        # the plate's height on the vehicle's height sensor, by the camera's last measured
        # frames: each one's distance above the magnet plus the height at its capture (their
        # mean: a drag-free filter's height is centimetres noisy on a range sensor 2 m from
        # the floor). The plate does not move, so it stands while the camera sees nothing;
        # only a measured frame moves it (an odometry that drifts while the plate holds the
        # vehicle would carry the plate away on paper)
        self._plate_words: deque[float] = deque(maxlen=PLATE_WORDS)
        self._heights: deque[tuple[float, float]] = deque(maxlen=HEIGHT_HISTORY)
        self._plate_above_m = math.inf  # the camera's last word on the plate's distance
        self._plate_seen_s = -math.inf  # that word's capture time (the pilot's clock)
        # when a fresh frame last put the plate further than contact_veto_m
        self._far_seen_t: float | None = None
        self._climbing_since: float | None = None  # a climb that may meet the plate began
        self._seats = SeatChecks()  # the magnet's hold tried before a stop (``seat_check``)
        self._touchdown = TouchdownDetector(
            s.touchdown_window_s, s.touchdown_still_m, s.landed_height_m, s.touchdown_speed_mps
        )
        self.last_t_s = 0.0
        self.last_sent_clock_s = -math.inf  # ``clock()`` when the last command went out
        # the last setpoint sent (its time, velocity, yaw rate and phase), to send again
        self._last_setpoint: tuple[float, Array, float, str | None] | None = None
        # frames, odometry samples and the pilot's clock arrive on different threads
        self._lock = threading.RLock()
        self._frame_clock: tuple[float, float] | None = None  # (frame t_s, clock() then)
        if height_m is None:
            self.report(
                "pilot: no height source, so no contact or touchdown evidence: the motors are "
                "never stopped on the plate, a final climb backs off after "
                f"{self.controller.settings.commit_timeout_s:g} s, and a landing is handed to "
                "the vehicle's own or descends until it is stopped"
            )

    # -- state ----------------------------------------------------------------------------

    def _enter(self, state: PilotState, t_s: float, why: str) -> None:
        if state != self.state:
            self.transitions.append((t_s, self.state, state))
            self.report(f"pilot: {self.state} -> {state} at t = {t_s:.2f} s ({why})")
            before, self.state = self.state, state
            if before == PilotState.WAITING and state in FLYING:
                self._raise_velocity_gain()
            elif state == PilotState.RELEASED:
                self._restore_velocity_gain()

    def _raise_velocity_gain(self) -> None:
        """Take over with the velocity loop of ``PilotSettings.velocity_gain_per_s`` where the
        commander can set it; the controller then models that gain. Not on a vehicle whose
        estimator models no drag (``lean_lag_s`` > 0, the Crazyflie's Kalman filter): its
        velocity is off by what gusts push, and a stiffer loop flies more of that error."""
        gain = self.settings.velocity_gain_per_s
        if gain is None or not isinstance(self.commander, VelocityGainSetter):
            return
        if self.settings.command == "attitude" and isinstance(self.commander, AttitudeSender):
            return  # the horizontal velocity loop is the pilot's own
        if self.settings.lean_lag_s > 0:
            self.report(
                "pilot: the vehicle's estimator models no drag: its own velocity gain is kept "
                f"({self.controller.settings.onboard_velocity_gain:g} /s)"
            )
            return
        if self.commander.set_velocity_gain(gain):
            self.controller.use_velocity_gain(gain)
            self._gain_raised = True
        else:
            self.report(
                f"pilot: the vehicle's velocity gain could not be set to {gain:g} /s: flying "
                f"on its own ({self.controller.settings.onboard_velocity_gain:g} /s)"
            )

    def _restore_velocity_gain(self) -> None:
        """The vehicle's own velocity gain back, once the motors stopped or it was handed back
        (after a link loss nothing reaches it: it keeps the raised gain until it restarts)."""
        if self._gain_raised and isinstance(self.commander, VelocityGainSetter):
            self.commander.restore_velocity_gain()
            self._gain_raised = False

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

    def exclusive(self) -> threading.RLock:
        """The pilot's lock: held, no frame, tick or odometry sample moves the pilot (and no
        setpoint goes out) on another thread; e.g. around a link's last command and the
        release that follows it, so no tick slips a setpoint in after the last one."""
        return self._lock

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
        command = self.settings.command
        sent = (command == "full-state" and self._send_full_state(sp)) or (
            command == "attitude" and self._send_attitude(t_s, sp)
        )
        if not sent:
            self._lean_watch.restart()  # the vehicle's own loop sets its lean meanwhile
            self.commander.send_velocity(sp.v_mps, sp.yaw_rate_rad_s)
        return self._sent(t_s, (v, yaw_rate_rad_s, phase), sp)

    def _sent(self, t_s: float, asked: tuple[Array, float, str | None], sp: Setpoint) -> PilotStep:
        """A setpoint went out at ``t_s``: when (on ``clock``), and what was asked (velocity,
        yaw rate, phase), to send again; the step reports ``sp`` (as sent, or as what was sent
        amounts to)."""
        self.last_sent_clock_s = self.clock()
        self._last_setpoint = (t_s, *asked)
        return PilotStep(t_s, self.state, sp.v_mps, sp.yaw_rate_rad_s, asked[2])

    def _send_full_state(self, sp: Setpoint) -> bool:
        """``sp`` as a full-state setpoint (``PilotSettings.command``): the position and yaw
        that the vehicle's own loops, holding them from its estimate, fly at ``sp``'s velocity
        and yaw rate. False where it cannot be sent (the velocity is sent instead): a vehicle
        link that takes none (said once), no odometry yet, or odometry too old to place a
        position by (older than ``stale_after_s``: a hover is then a zero velocity, not a
        return to where the vehicle was)."""
        if not isinstance(self.commander, FullStateSender):
            self._say_velocity_only()
            return False
        p_now = self._position_now(self._motion())
        if p_now is None:
            return False
        s = self.settings
        p_sp = p_now + np.asarray(sp.v_mps, np.float64) / s.position_gain_per_s
        yaw_sp = yaw_rad(np.asarray(self.attitude())) + sp.yaw_rate_rad_s / s.yaw_gain_per_s
        p = (float(p_sp[0]), float(p_sp[1]), float(p_sp[2]))
        self.commander.send_full_state(p, sp.v_mps, yaw_sp, sp.yaw_rate_rad_s)
        return True

    def _send_attitude(self, t_s: float, sp: Setpoint) -> bool:
        """``sp`` as an attitude setpoint (``PilotSettings.command``): the lean the pilot's own
        velocity loop asks for ``sp``'s horizontal velocity (``control.attitude_command``, on
        the velocity the controller knows best and the accelerometer's push), the yaw rate,
        and the height that the vehicle's own loop, holding it from its estimate, climbs to
        at ``sp``'s vertical speed. False where it cannot be sent (the velocity is sent
        instead): as for a full-state setpoint, where the attitude is older than
        ``stale_after_s`` or not finite, and for good once the vehicle did not fly the lean
        sent (``control.lean_follow``: its attitude loop takes an angle with another sign
        than the pilot's)."""
        if not isinstance(self.commander, AttitudeSender):
            self._say_velocity_only()
            return False
        if self._lean_watch.broken is not None:
            return False
        motion = self._motion()
        p_now = self._position_now(motion)
        fresh = self._age("attitude") < self.settings.stale_after_s
        if motion is None or p_now is None or not fresh:
            return False
        # the vehicle holds its own estimate of its attitude at the lean sent: where that
        # estimate misses the lean a push needs (``lean_lag_s``), the lean sent is the one
        # wanted less what the estimate misses
        R_own = np.asarray(self.attitude(), np.float64)
        R_world_body = self._attitude(t_s)
        odometry = self._odometry(t_s, motion, R_world_body)
        v_now = self.controller.horizontal_velocity_mps(odometry)
        push = None if odometry.push_mps2 is None else odometry.push_mps2[:2]
        roll, pitch = roll_pitch_rad(R_world_body)
        yaw = yaw_rad(R_world_body)
        # the acceleration the vehicle's lean gives it now (the push is added in the loop);
        # none within the plate's reach, whose touch holds the vehicle whatever its lean
        a_now = None
        in_reach = self._plate_in_reach(t_s)
        if not in_reach:
            a_now = GRAVITY_MPS2 * np.array(leaned(roll, pitch, yaw))
        lean = self._lean_loop.lean(t_s, sp.v_mps, v_now, push, yaw, t_s - odometry.t_s, a_now)
        roll_own, pitch_own = roll_pitch_rad(R_own)
        z_m = float(p_now[2]) + sp.v_mps[2] / self.settings.position_gain_per_s
        sent = (lean.roll_rad - (roll - roll_own), lean.pitch_rad - (pitch - pitch_own), z_m)
        if not all(math.isfinite(x) for x in sent):
            return False  # an attitude that is not known: the velocity goes instead
        own = (roll_own, pitch_own)
        if self._lean_watch.update(t_s, (sent[0], sent[1]), own, watch=not in_reach):
            self._refuse_attitudes(t_s)
            return False
        self.commander.send_attitude(sent[0], sent[1], sp.yaw_rate_rad_s, sent[2])
        return True

    def _refuse_attitudes(self, t_s: float) -> None:
        """The vehicle did not fly the lean sent: velocity setpoints from now on, which its
        own loops fly, with the offsets the controller gives them."""
        self.controller.use_lean_command(False)
        self.report(
            f"pilot: the vehicle does not fly the lean sent at t = {t_s:.2f} s "
            f"({self._lean_watch.detail}): velocity setpoints from now on. Check the sign "
            "its firmware takes for that angle (cflib's send_zdistance_setpoint sends pitch "
            "nose up positive)"
        )

    def _say_velocity_only(self) -> None:
        if not self._velocity_only_said:
            self._velocity_only_said = True
            self.report(
                "pilot: this vehicle's link takes velocity setpoints only: "
                f"{self.settings.command} setpoints are sent as velocities"
            )

    def _position_now(self, motion: tuple[Array, Array] | None) -> Array | None:
        """The odometry's position (``motion``, the latest sample) carried to now by its
        velocity (it is a sample old); None without odometry, or with odometry too old to
        place a position by (older than ``stale_after_s``: a hover is then a zero velocity,
        not a return to where the vehicle was)."""
        age_s = self._age("position")
        if motion is None or not age_s < self.settings.stale_after_s:
            return None
        return carried(Odometry(-age_s, motion[0], motion[1]), 0.0)

    def _stop(self, t_s: float, state: PilotState, why: str) -> PilotStep:
        self._enter(state, t_s, why)  # first: a commander may ask which stop this is
        self.commander.send_stop()
        self._restore_velocity_gain()
        return PilotStep(t_s, self.state, None, None, None)

    # -- the magnet's hold ----------------------------------------------------------------

    @property
    def leans_refused(self) -> bool:
        """The vehicle did not fly the leans sent: velocities since (``control.lean_follow``)."""
        return self._lean_watch.broken is not None

    @property
    def seat_drops(self) -> int:
        """The checks of the magnet's hold the vehicle came down in (``control.seat_check``)."""
        return self._seats.drops

    def _try_seat(self, t_s: float, why: str) -> PilotStep:
        """Contact evidence ``why``: try the magnet's hold before the motors stop
        (``control.seat_check``), or stop them at once where ``seat_check_s`` is 0."""
        if self.settings.seat_check_s <= 0.0:
            return self._stop(t_s, PilotState.PERCHED, why)
        self._seats.now = SeatCheck(t_s, self._seat_height(t_s), why)
        return self._seat_step(t_s)

    def _seat_height(self, t_s: float) -> float | None:
        """The live height at ``t_s``, fitted over the last tenths of a second (None where
        no live height is now)."""
        return None if self._height() is None else self._height_at(t_s)

    def _seat_step(self, t_s: float) -> PilotStep:
        """One step of the check: the motors stop once the magnet held the vehicle through
        it; a vehicle that came down is flown on (the controller backs off, or the landing
        goes on); else the check's setpoint goes out again (the level thrust, reported in the
        step as the descent it amounts to, or the descent)."""
        seat, s = self._seats.now, self.settings
        assert seat is not None
        f_body = None if self.specific_force is None else self.specific_force()
        f_z = None if f_body is None else float(np.asarray(f_body, np.float64)[2])
        limits = (s.seat_check_s, s.seat_drop_m, s.seat_fall_mps2)
        verdict = seat.verdict(t_s, self._seat_height(t_s), f_z, limits)
        if verdict == SeatVerdict.HELD:
            self._seats.now = None
            return self._stop(t_s, PilotState.PERCHED, f"{seat.why}; the magnet held it")
        if verdict == SeatVerdict.DROPPED:
            return self._seat_dropped(t_s, seat)
        if not isinstance(self.commander, ThrustSender):
            return self._send(t_s, np.array([0.0, 0.0, -s.seat_check_mps]), 0.0, SEAT_CHECK)
        # the thrust itself, under the hover's: a descent asked of the vehicle's own loop
        # takes off only what its loop's floor lets it (the firmware's PID: half the hover)
        self._lean_watch.restart()
        self.commander.send_level_thrust(s.seat_check_thrust)
        down = np.array([0.0, 0.0, -s.seat_check_mps])
        return self._sent(t_s, (down, 0.0, SEAT_CHECK), safe_setpoint(down, 0.0, s.limits))

    def _seat_dropped(self, t_s: float, seat: SeatCheck) -> PilotStep:
        """The vehicle came down when asked: the magnet does not hold it. Perching, the
        controller backs off for another final climb (or gives up: a landing); landing, the
        landing goes on."""
        self._seats.now = None
        self._seats.drops += 1
        self._contact.reset()
        self._reset_held()
        self._climbing_since = None
        what = (
            f"{seat.drop_m * 100:.0f} cm in {t_s - seat.started_s:.2f} s"
            if seat.falling < FALLING_READINGS
            else f"its accelerometer read a fall {t_s - seat.started_s:.2f} s in"
        )
        if self.state == PilotState.LANDING:
            self.report(
                f"pilot: the magnet did not hold the vehicle at t = {t_s:.2f} s (it came down: "
                f"{what}): landing on"
            )
            return self._land_step(t_s)
        phase = self.controller.back_off(t_s)
        then = (
            "giving up: landing"
            if phase == Phase.GIVE_UP
            else f"backing off for another final climb ({self.controller.tries} failed)"
        )
        self.report(
            f"pilot: the magnet did not hold the vehicle at t = {t_s:.2f} s (it came down: "
            f"{what}, after: {seat.why}): {then}"
        )
        if phase == Phase.GIVE_UP:
            self._start_landing(t_s, f"gave up after {self.controller.tries} final climbs")
            return self._land_step(t_s)
        return self._send(t_s, np.zeros(3), 0.0, Phase.RETREAT)

    def _start_landing(self, t_s: float, why: str) -> None:
        self._landing_since = t_s
        self._seats.now = None
        self._landing_said = None
        self._touchdown.reset()
        self._reset_held()
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

    def _note_height(self, t_s: float) -> None:
        """Keep the live height at ``t_s`` (a frame's word on the plate is paired with the
        height at its capture)."""
        height = self._height()
        if height is not None and (not self._heights or t_s >= self._heights[-1][0]):
            self._heights.append((t_s, height))

    def _height_at(self, t_s: float) -> float | None:
        """The live height at ``t_s``: the least-squares line through the heights kept within
        ``HEIGHT_FIT_S`` of it, at ``t_s`` (a drag-free filter's height on a range sensor 2 m
        from the floor is a centimetre noisy from one sample to the next, and the vehicle may
        be climbing); the nearest kept sample where there are too few, the height now where
        none is kept."""
        if not self._heights:
            return self._height()
        near = [(t, h) for t, h in self._heights if abs(t - t_s) <= HEIGHT_FIT_S]
        if len(near) < 3:
            return newest_at(self._heights, t_s)
        return line_at(near, t_s)

    def _height_age(self) -> float:
        """Seconds since the vehicle's last height sample (infinite without a height)."""
        if self.height_m is None:
            return math.inf
        return 0.0 if self.ages is None else self.ages().height_s

    def _motion(self) -> tuple[Array, Array] | None:
        """The vehicle's position and velocity, None if unknown or not finite."""
        motion = self.odometry() if self.odometry is not None else None
        if motion is None or not (
            np.all(np.isfinite(motion[0])) and np.all(np.isfinite(motion[1]))
        ):
            return None
        return motion

    def _attitude(self, t_s: float) -> Array:
        """The vehicle's attitude, with the lean its estimate misses taken out where it is
        drag-free (``PilotSettings.lean_lag_s``), and there blended with the integrated gyro
        where the link gives it (``PilotSettings.gyro_blend_s``)."""
        R_world_body = np.asarray(self.attitude(), np.float64)
        if self.lean is None or not np.all(np.isfinite(R_world_body)):
            return R_world_body
        f_body = None if self.specific_force is None else self.specific_force()
        # with the plate within held_within_m its touch and the magnet's pull reach the
        # accelerometer too: the lean is held as it was
        reach = self._plate_in_reach(t_s)
        R_world_body = self.lean.correct(R_world_body, None if reach else f_body, t_s)
        gyro = None if self.gyro is None else self.gyro()
        if self.blend is None or gyro is None:
            return R_world_body
        return self.blend.blend(R_world_body, gyro, t_s)

    def _odometry(self, t_s: float, motion: tuple[Array, Array], R_world_body: Array) -> Odometry:
        """The odometry for the controller: the motion, and the accelerometer's push turned
        into the world frame by the attitude (None where there is no finite sample)."""
        f_body = None if self.specific_force is None else self.specific_force()
        push = None
        if f_body is not None and np.all(np.isfinite(f_body[:2])):
            f_xy = np.array([f_body[0], f_body[1], 0.0], np.float64)
            push = np.asarray(R_world_body, np.float64) @ f_xy
            push[2] = 0.0
        full = None
        if f_body is not None and len(f_body) == 3 and np.all(np.isfinite(f_body)):
            full = np.asarray(f_body, np.float64)
        return Odometry(t_s - self._age("position"), motion[0], motion[1], push, full)

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

    @staticmethod
    def _old(name: str, age_s: float) -> str:
        if math.isinf(age_s):
            return f"no {name} from the vehicle"
        return f"the vehicle's {name} is {age_s:.1f} s old"

    def _hold(self, t_s: float, name: str, age_s: float) -> PilotStep:
        """A stale sense: hover (no climb) until it is fresh; land or release once lost."""
        s = self.settings
        self._contact.reset()
        self._reset_held()
        self._seats.now = None  # a check needs a live height and the vehicle's own loop
        if age_s >= s.senses_lost_after_s:
            old = self._old(name, age_s)
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

    # -- the landing ----------------------------------------------------------------------

    def _say_landing(self, t_s: float, kind: str, what: str) -> None:
        """Say how the landing goes (``kind`` of news): at once when that changes, else every
        ``stuck_report_s``."""
        said = self._landing_said
        if said is None or said[1] != kind or t_s - said[0] >= self.settings.stuck_report_s:
            self.report(f"pilot: landing at t = {t_s:.2f} s: {what}")
            self._landing_said = (t_s, kind)

    def _land_step(self, t_s: float) -> PilotStep:
        """One step of a landing: a descent until touchdown is sensed, never a timer."""
        s = self.settings
        if self.on_ground is not None and self.on_ground():
            return self._stop(t_s, PilotState.LANDED, "the vehicle's land detector says landed")
        stale = self._stale(t_s)
        lost = stale is not None and stale[1] >= s.senses_lost_after_s
        height = None if lost else self._height()
        if height is None:
            self._touchdown.reset()
            gap = not lost and self._height_age() < s.senses_lost_after_s
            if not gap and self.commander.send_land():
                why = self._old(*stale) if stale is not None else "no live height"
                self._enter(PilotState.RELEASED, t_s, f"{why}: the autopilot's LAND lands it")
                return PilotStep(t_s, self.state, None, None, None)
            self._say_landing(
                t_s,
                "blind",
                "no live height to sense the touchdown: descending at "
                f"{s.land_speed_mps:g} m/s until one does",
            )
        else:
            motion = self._motion()
            vz = None if motion is None else float(motion[1][2])
            if self._touchdown.touched(t_s, height, vz):
                return self._stop(t_s, PilotState.LANDED, f"touchdown sensed at {height:.2f} m")
            if self._seats.now is not None:
                return self._seat_step(t_s)
            if self._held_landing(t_s, height):
                return self._try_seat(t_s, HELD_UP)
            since = self._landing_since if self._landing_since is not None else t_s
            if t_s - since >= s.stuck_report_s:
                self._say_landing(
                    t_s,
                    "stuck",
                    f"{t_s - since:.0f} s in, {height:.2f} m up and no touchdown yet: still "
                    "descending, the motors stay on",
                )
        return self._send(t_s, np.array([0.0, 0.0, -s.land_speed_mps]), 0.0, None)

    # -- frames and ticks -----------------------------------------------------------------

    def update(self, estimate: Estimate | None, t_s: float) -> PilotStep:
        """One frame: the estimate (None, not valid or too old: no target) at time ``t_s``.
        An estimate of a live frame (``captured_s`` known, on this pilot's ``clock``) moves
        the pilot's time on to its capture time plus the time since its capture, so its
        latency is counted and the controller places it at its capture time."""
        with self._lock:
            return self._update(estimate, t_s)

    def now(self) -> float | None:
        """The present moment on the frames' clock (the last frame's ``t_s`` plus the time
        since it was handed over); None before the first frame."""
        if self._frame_clock is None:
            return None
        t_frame, then = self._frame_clock
        return max(self.last_t_s, t_frame + max(0.0, self.clock() - then))

    def tick_now(self, quiet_s: float = 0.0) -> PilotStep | None:
        """``tick`` at the present moment (``now``): what a vehicle link calls on each
        state-estimate sample, and ``PilotClock`` at a fixed rate. ``quiet_s``: skip the tick
        when a command went out less than this long ago."""
        with self._lock:
            t_s = self.now()
            if t_s is None or self.clock() - self.last_sent_clock_s < quiet_s:
                return None
            return self.tick(t_s)

    def tick(self, t_s: float) -> PilotStep | None:
        """The pilot's clock at ``t_s`` (the frames' clock), between frames: the watchdogs,
        the landing, and while perching a setpoint from the controller's odometry loop
        (``PerchingController.between_frames``) with the contact check; where there is
        nothing to steer on, the last setpoint again once it is ``setpoint_period_s`` old
        (a camera that stalls leaves the vehicle hearing the pilot until the camera's
        watchdog acts). None when nothing was sent (waiting or done, or a setpoint went out
        within the period)."""
        with self._lock:
            if t_s < self.last_t_s or not self.flying:
                return None
            self.last_t_s = t_s
            self._note_height(t_s)
            if self.state == PilotState.LANDING:
                return self._land_step(t_s)
            stale = self._stale(t_s)
            if stale is not None:
                return self._hold(t_s, *stale)
            if self._frame_t is not None and t_s - self._frame_t > self.settings.frame_timeout_s:
                return self._silent(t_s)
            if self._seats.now is not None:
                return self._seat_step(t_s)
            step = self._between_frames(t_s) if self.state == PilotState.PERCHING else None
            return step if step is not None else self._again(t_s)

    def _again(self, t_s: float) -> PilotStep | None:
        """The last setpoint again, where it is ``setpoint_period_s`` old or more."""
        last = self._last_setpoint
        if last is None or t_s - last[0] < self.settings.setpoint_period_s:
            return None
        return self._send(t_s, last[1], last[2], last[3])

    def _between_frames(self, t_s: float) -> PilotStep | None:
        """While perching with frames coming: the controller's odometry loop and the contact
        check (None: no odometry, or nothing held to steer on)."""
        motion = self._motion()
        if motion is None:
            return None
        R_world_body = self._attitude(t_s)
        odometry = self._odometry(t_s, motion, R_world_body)
        command = self.controller.between_frames(t_s, R_world_body, odometry, self._age("attitude"))
        if command is None:
            return None
        pressing = self._pressing(command, t_s)
        contact = self._contact_evidence(command, t_s, pressing, seen=False)
        if contact is not None:
            return self._try_seat(t_s, contact)
        return self._send(t_s, command.v_mps, command.yaw_rate_rad_s, command.phase)

    def _contact_evidence(
        self, command: Command, t_s: float, pressing: bool, *, seen: bool
    ) -> str | None:
        """What says the vehicle is against the plate (None: nothing): a climb, ``pressing``
        into it, whose height stopped rising (unless, in the final climb, a fresh frame of the
        last contact window put the plate further than ``contact_veto_m``), or a height the
        magnet holds still.
        ``seen``: the command rests on a fresh camera estimate (not on the odometry alone)."""
        error = command.error_m
        if (
            seen
            and command.phase == Phase.COMMIT
            and error is not None
            and float(error[2]) > self.settings.contact_veto_m
        ):
            self._far_seen_t = t_s
        far = self._far_seen_t is not None and (
            t_s - self._far_seen_t < self.settings.contact_window_s
        )
        if pressing and self._contact.touched(t_s, self._height()) and not far:
            return _stopped_against(command)
        return HELD_UP if self._held_up(command, t_s) else None

    def _held_up(self, command: Command, t_s: float) -> bool:
        """Contact evidence near the plate in any phase (a back-off, or steps down out of the
        capture cone and climbs again, where the camera's evidence at a few centimetres says
        the vehicle is off-centre; a blind climb the magnet caught): with the plate within
        reach (``_plate_in_reach``), the vertical speeds asked for over ``held_window_s``
        would have moved the vehicle twice ``held_still_m`` and its height has stayed within
        ``held_still_m``, and it is still at the plate's height (``_at_plate_height``): the
        magnet holds it against the plate (the motors cannot pull it off)."""
        return self._held_at(t_s, self._height(), command.climb_asked_mps)

    def _held_at(self, t_s: float, height_m: float | None, asked_z_mps: float) -> bool:
        """The held window with this height and the vertical speed asked: held while the plate
        is within reach (else the window starts again) and the vehicle at its height. On the
        camera's own recent word (``_caught``) also over the shorter ``caught_window_s``, a
        height that moved against the asking counting as held; never on the height's alone,
        and never while the accelerometer says the vehicle moves (``_rigid``: a vehicle in
        free air whose filter's drift holds it at the plate's height). Without the camera's
        recent word the vehicle must also be level (``_level``): one leaning into the wind
        beside the plate may be steady enough to read rigid."""
        self._rigid.add(t_s, None if self.specific_force is None else self.specific_force())
        at_plate = self._at_plate_height(t_s)
        if not self._plate_in_reach(t_s, at_plate):
            self._reset_held()
            return False
        held = self._held.touched(t_s, height_m, asked_z_mps)
        if self._caught(t_s):
            caught = self._caught_held.touched(t_s, height_m, asked_z_mps, against=True)
        else:
            self._caught_held.reset()
            caught = False
            held = held and self._level(t_s)
        return (held or caught) and at_plate and self._rigid.rigid(t_s) is not False

    def _level(self, t_s: float) -> bool:
        """The vehicle leans less than ``held_level_deg`` (an attitude not known: not
        level)."""
        R_world_body = self._attitude(t_s)
        if not np.all(np.isfinite(R_world_body)):
            return False
        return lean_deg(R_world_body) < self.settings.held_level_deg

    def _reset_held(self) -> None:
        self._held.reset()
        self._caught_held.reset()

    def _caught(self, t_s: float) -> bool:
        """The camera's last measured frame put the plate within the magnet's reach
        (``held_within_m``) no longer than two caught windows ago: the vehicle was at the plate
        a moment before. There a height drifting against the asking is the filter's (the
        plate holds the vehicle); a vehicle unseen for longer, or only at the plate's height
        by its own height sensor, may be beside the plate, where a gust or the filter's
        drift lifts it against the asking in free air."""
        s = self.settings
        recent = t_s - self._plate_seen_s <= 2.0 * s.caught_window_s
        return recent and self._plate_above_m < s.held_within_m

    def _plate_in_reach(self, t_s: float, at_plate: bool | None = None) -> bool:
        """The plate is within the magnet's reach (``held_within_m``) by the camera's last
        measured frame, or the vehicle is at the plate's height by the frames
        (``_at_plate_height``, or ``at_plate`` where already known: a vehicle that climbed
        the last centimetres blind)."""
        if self._plate_above_m < self.settings.held_within_m:
            return True
        if at_plate is None:
            at_plate = self._at_plate_height(t_s)
        return bool(self._plate_words) and at_plate

    @property
    def _plate_height_m(self) -> float | None:
        """The plate's height by the camera's measured frames (their words' mean)."""
        words = self._plate_words
        return sum(words) / len(words) if words else None

    def _at_plate_height(self, t_s: float) -> bool:
        """The height now (``_height_at``: fitted to the last tenths of a second) is within
        ``held_height_m`` (the height sensor's own error) of the plate's height by the
        camera's measured frames (True where either is unknown): a vehicle that came off the
        plate and hovers unseen below it is not at the plate."""
        plate = self._plate_height_m
        height = None if plate is None else self._height_at(t_s)
        if plate is None or height is None:
            return True
        return abs(plate - height) < self.settings.held_height_m

    def _camera_puts_plate(self, estimate: Estimate) -> None:
        """A measured frame's word on the plate: how far above the magnet it puts it, along
        the body's z through the mount (no attitude needed, which may be the sense that was
        lost), and that plus the height at the frame's capture: the plate's height. A word
        further than ``held_height_m`` from the mean of those before starts them again (the
        plate has moved on the height sensor: a height that jumped, another marker). A gap
        wider than ``held_gap_m`` starts the held window again: the magnet has not closed it."""
        above_m = self.controller.target_above_magnet_m(estimate)
        self._plate_above_m = above_m
        self._plate_seen_s = self.controller.capture_time(estimate)
        if above_m > self.settings.held_gap_m:
            self._reset_held()
        height = self._height_at(self._plate_seen_s)
        if height is None:
            return
        word, plate = height + above_m, self._plate_height_m
        if plate is not None and abs(word - plate) >= self.settings.held_height_m:
            self._plate_words.clear()
        self._plate_words.append(word)

    def _held_landing(self, t_s: float, height_m: float) -> bool:
        """Contact evidence while landing: the plate within the magnet's reach
        (``_plate_in_reach``), the height held still against the descent for
        ``held_window_s`` and still the plate's (``_at_plate_height``): the magnet caught the
        vehicle before the landing, which it cannot leave."""
        return self._held_at(t_s, height_m, -self.settings.land_speed_mps)

    def _pressing(self, command: Command, t_s: float) -> bool:
        """The command climbs into the plate, so that a height that stops rising is contact:
        the final climb, or a climb at its speed or faster with the plate within
        ``climb_contact_within_m`` by the camera that has gone on for a contact window (a
        vehicle still turning from a descent to the climb rises little at first)."""
        if command.phase == Phase.COMMIT:
            return True
        climb_mps = self.controller.settings.commit_speed_mps
        if not (
            command.phase == Phase.CLIMB
            and command.error_m is not None
            and float(command.v_mps[2]) >= climb_mps - 1e-9
            and float(command.error_m[2]) < self.settings.climb_contact_within_m
        ):
            self._climbing_since = None
            return False
        if self._climbing_since is None:
            self._climbing_since = t_s
        return t_s - self._climbing_since >= self.settings.contact_window_s

    def _silent(self, t_s: float) -> PilotStep:
        """The camera's watchdog: no frame for ``frame_timeout_s``; each tick flies as a frame
        without the target (hold on odometry, then lost, then land)."""
        if not self._camera_silent:
            self._camera_silent = True
            self.silences += 1
            last = self._frame_t if self._frame_t is not None else t_s
            self.report(
                f"pilot: no frame since t = {last:.2f} s (watchdog "
                f"{self.settings.frame_timeout_s:g} s): flying on as if the target were lost "
                f"(hold on odometry, then lost; landing {self.settings.land_after_lost_s:g} s "
                "after the last sighting)"
            )
        return self._fly(None, t_s, seen=False)

    def _update(self, estimate: Estimate | None, t_s: float) -> PilotStep:
        if estimate is not None and math.isfinite(estimate.captured_s):
            # a live frame: now is its capture time plus the time since then (the estimate's
            # latency), not the frame's own time, on the frames' clock
            t_s = max(t_s, estimate.t_s + max(0.0, self.clock() - estimate.captured_s))
        t_s = max(t_s, self.last_t_s)
        self.last_t_s = t_s
        self._note_height(t_s)
        self._frame_clock = (t_s, self.clock())
        self._frame_t = t_s
        if self._camera_silent:
            self._camera_silent = False
            self.report(f"pilot: frames again at t = {t_s:.2f} s")
        limit_s = self.controller.settings.max_estimate_age_s
        fresh = usable(estimate, t_s, limit_s)
        if self.state == PilotState.WAITING:
            if not fresh:
                return PilotStep(t_s, self.state, None, None, None)
            self._enter(PilotState.PERCHING, t_s, "target in view")
        if self.state in DONE:
            return PilotStep(t_s, self.state, None, None, None)
        if self.state == PilotState.LANDING:
            if fresh and estimate is not None and estimate.age_s <= 0.0:
                self._camera_puts_plate(estimate)
            return self._land_step(t_s)
        if fresh:
            self._last_valid_t = t_s
        stale = self._stale(t_s)
        if stale is not None:
            return self._hold(t_s, *stale)
        if self._holding:
            self.report(f"pilot: the vehicle's samples are fresh again at t = {t_s:.2f} s")
            self._holding = False
        return self._fly(estimate, t_s, seen=fresh)

    def _fly(self, estimate: Estimate | None, t_s: float, *, seen: bool) -> PilotStep:
        """The controller's command for ``estimate`` (None: no target) at ``t_s``; ``seen``:
        the estimate is fresh (``usable``, as the frame's update found it)."""
        motion = self._motion()
        R_world_body = self._attitude(t_s)
        odometry = None if motion is None else self._odometry(t_s, motion, R_world_body)
        command: Command = self.controller.update(
            estimate, t_s, R_world_body, odometry, self._age("attitude")
        )
        self._send_fix(command)
        if seen and estimate is not None and estimate.age_s <= 0.0:
            # a measurement of this frame (not the estimator coasting): the camera's word on
            # the plate, by its own distance through the mount (the command's error is the
            # odometry's, which drifts while the plate holds the vehicle)
            self._camera_puts_plate(estimate)
        return self._follow(command, t_s, seen=seen)

    def _send_fix(self, command: Command) -> None:
        """Hand the vehicle's estimator the position this frame's fix says, where it takes
        them (said once where it does not)."""
        fix = command.position_fix_m
        if (
            fix is None
            or not self._fixes_taken
            or not isinstance(self.commander, PositionFixSender)
        ):
            return
        x, y, z = (float(v) for v in fix)
        if not self.commander.send_position_fix((x, y, z)):
            self._fixes_taken = False
            self.report("pilot: the vehicle takes no position fixes: its estimator flies alone")

    def _follow(self, command: Command, t_s: float, *, seen: bool) -> PilotStep:
        """The state the controller's command leads to, and the setpoint sent in it
        (``seen``: it rests on a fresh camera estimate)."""
        s = self.settings
        if self._seats.now is not None:
            return self._seat_step(t_s)
        if command.phase == Phase.GIVE_UP:
            tries = self.controller.tries
            self._start_landing(t_s, f"gave up after {tries} final climbs without contact")
            return self._land_step(t_s)
        pressing = self._pressing(command, t_s)
        contact = self._contact_evidence(command, t_s, pressing, seen=seen)
        if contact is not None:
            return self._try_seat(t_s, contact)
        if command.phase == Phase.COMMIT:
            self._enter(PilotState.PERCHING, t_s, "final climb")
        else:
            if not pressing:
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
        clock: Callable[[], float] | None = None,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        """Finish a landing in real time (after ``abort`` or a lost target): a tick every
        ``setpoint_period_s`` until touchdown is sensed or the vehicle is handed over. It
        returns only then: a vehicle that never comes down keeps being flown (and said so)
        until the caller is interrupted."""
        clock = clock or self.clock
        t0 = clock() - self.last_t_s
        while self.state == PilotState.LANDING:
            self.tick(clock() - t0)
            sleep(self.settings.setpoint_period_s)


SEAT_CHECK = "seat-check"  # the phase of the setpoints that try the magnet's hold
HELD_UP = (
    "near the plate the height held still against what was asked: the magnet holds the vehicle"
)


def _stopped_against(command: Command) -> str:
    what = "final climb" if command.phase == Phase.COMMIT else "climb"
    return f"the {what} stopped against the plate"
