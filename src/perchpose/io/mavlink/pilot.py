"""Perching with an autopilot: the perching pilot's setpoints as MAVLink velocity targets.

``MavlinkPilot`` runs the same ``PerchingPilot`` (controller and safety states) as the Crazyflie
link, on a ``MavlinkLink``: its world frame is the autopilot's local frame turned z-up (NWU:
x north, y west, z up; ``p_nwu = diag(1, -1, -1) p_ned``), its body frame FLU from the
vehicle's FRD, its odometry the vehicle's LOCAL_POSITION_NED and its attitude ATTITUDE. Each
setpoint goes out as ``SET_POSITION_TARGET_LOCAL_NED`` in ``MAV_FRAME_LOCAL_NED`` with only
velocity and yaw rate used (type mask 1479), which ArduCopter's GUIDED and PX4's OFFBOARD both
follow.

Where the autopilot streams HIGHRES_IMU (PX4; ArduPilot builds that carry it), the pilot reads
its accelerometer as the Crazyflie link reads ``acc.x/y/z``: along the body's x and y the thrust
has no part, so they are the air's push over the mass, which the controller leans the velocity
setpoint against as it comes (``ControllerSettings.push_feedforward``) and its inertial filter
turns into the world (``control.inertial``). A vehicle that does not send it is flown without
(said once, after the link has asked for it three times).

The autopilot stays in charge:
- the pilot takes over only while the vehicle is armed and its HEARTBEAT says GUIDED
  (ArduPilot Copter, custom mode 4) or OFFBOARD (PX4, main mode 6); no controller setpoint is
  ever sent in another mode;
- it flies one vehicle: ``target_system``, or the first autopilot heard; nothing from another
  system reaches its state, its setpoints or its release logic (``perchpose.io.mavlink.link``);
- it stops (state ``released``, nothing more sent, said once) when the vehicle leaves that
  mode (its HEARTBEAT is asked for at ``HEARTBEAT_HZ``, so that a mode change is heard within
  0.1 s where the autopilot honours it: ArduPilot does, PX4 keeps 1 Hz), disarms, its
  HEARTBEAT stops for ``heartbeat_timeout_s``, or its ATTITUDE or
  LOCAL_POSITION_NED is older than ``PilotSettings.senses_lost_after_s`` (older than
  ``stale_after_s``, the pilot only hovers until they are fresh): the autopilot's own mode or
  failsafe then flies the vehicle; a non-finite sample is dropped, never flown on;
- PX4 switches into OFFBOARD only while a setpoint stream is already coming in (more than 2 Hz
  for a second): while the pilot waits, an armed PX4 vehicle gets a zero-velocity setpoint at
  ``proof_of_life_hz``, which outside OFFBOARD it ignores and inside holds it still;
- contact on the plate force-disarms (MAV_CMD_COMPONENT_ARM_DISARM with 21196: the magnet
  holds the vehicle, and an autopilot's land detector does not know a ceiling); landed asks a
  normal disarm, which the autopilot refuses unless its land detector agrees; a landing ends on
  the pilot's own touchdown rule or on the autopilot's land detector (EXTENDED_SYS_STATE
  ON_GROUND, where the autopilot sends it: it is heard, not asked for), whichever comes first;
- ``close`` (end of the video, Ctrl-C) sends one zero-velocity setpoint and then nothing:
  ArduCopter holds position in GUIDED, PX4 leaves OFFBOARD after ``COM_OF_LOSS_T`` for its
  offboard-loss action; a pilot that was landing hands the vehicle to the autopilot's LAND
  instead (a hover would hold it where the landing left it).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from perchpose.control.controller import PerchingController
from perchpose.control.pilot import PerchingPilot, PilotSettings, PilotState, SenseAges
from perchpose.control.pilot_clock import PilotClock
from perchpose.io.mavlink.link import MavlinkLink, VehicleState
from perchpose.values import Estimate

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
COPTER_MODE_GUIDED = 4
PX4_MAIN_MODE_OFFBOARD = 6
MAV_FRAME_LOCAL_NED = 1
# SET_POSITION_TARGET_LOCAL_NED: ignore position (1, 2, 4), acceleration (64, 128, 256) and yaw
# (1024): velocity and yaw rate only
VELOCITY_YAW_RATE_MASK = 1479
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_DO_SET_MODE = 176
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
COPTER_MODE_LAND = 9
PX4_MAIN_MODE_AUTO, PX4_AUTO_LAND = 4, 6
FORCE_DISARM = 21196.0
# the rate asked of the vehicle's HEARTBEAT, the one message that says its mode: a mode change
# by its pilot is heard within 0.1 s where the autopilot honours it (ArduPilot; PX4 keeps 1 Hz)
HEARTBEAT_HZ = 10.0
F = np.diag([1.0, -1.0, -1.0])  # NED <-> NWU and FRD <-> FLU


def setpoint_mode(vehicle: VehicleState) -> str | None:
    """The name of the mode the vehicle must be in to take our setpoints (None: an autopilot
    this module does not know)."""
    if vehicle.autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return "GUIDED"
    if vehicle.autopilot == MAV_AUTOPILOT_PX4:
        return "OFFBOARD"
    return None


def takes_setpoints(vehicle: VehicleState) -> bool:
    """The vehicle's last HEARTBEAT says GUIDED (ArduPilot) or OFFBOARD (PX4)."""
    if vehicle.autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return vehicle.custom_mode == COPTER_MODE_GUIDED
    if vehicle.autopilot == MAV_AUTOPILOT_PX4:
        return (vehicle.custom_mode >> 16) & 0xFF == PX4_MAIN_MODE_OFFBOARD
    return False


def _velocity_send(
    mav: Any, *, system: int, v_ned: tuple[float, float, float], yaw_rate_rad_s: float
) -> None:
    time_boot_ms = int(time.monotonic() * 1000) & 0xFFFFFFFF
    mav.set_position_target_local_ned_send(
        time_boot_ms,
        system,
        1,
        MAV_FRAME_LOCAL_NED,
        VELOCITY_YAW_RATE_MASK,
        0.0,
        0.0,
        0.0,
        *v_ned,
        0.0,
        0.0,
        0.0,
        0.0,
        yaw_rate_rad_s,
    )


def _disarm_send(mav: Any, *, system: int, force: bool) -> None:
    mav.command_long_send(
        system,
        1,
        MAV_CMD_COMPONENT_ARM_DISARM,
        0,
        0.0,
        FORCE_DISARM if force else 0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
    )


def land_mode(vehicle: VehicleState) -> tuple[float, float] | None:
    """MAV_CMD_DO_SET_MODE's custom mode and sub mode for the autopilot's own LAND (None: an
    autopilot this module does not know)."""
    if vehicle.autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return float(COPTER_MODE_LAND), 0.0
    if vehicle.autopilot == MAV_AUTOPILOT_PX4:
        return float(PX4_MAIN_MODE_AUTO), float(PX4_AUTO_LAND)
    return None


def _land_send(mav: Any, *, system: int, mode: tuple[float, float]) -> None:
    mav.command_long_send(
        system,
        1,
        MAV_CMD_DO_SET_MODE,
        0,
        float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
        *mode,
        0.0,
        0.0,
        0.0,
        0.0,
    )


class SetpointCommander:
    """The pilot's ``VehicleCommander`` (world z up, rad/s) as MAVLink velocity setpoints in
    NED, sent only while ``allowed()``; ``force_stop()`` says whether a stop is a forced
    disarm."""

    def __init__(
        self,
        link: MavlinkLink,
        allowed: Callable[[], bool],
        force_stop: Callable[[], bool],
    ) -> None:
        self.link = link
        self.allowed = allowed
        self.force_stop = force_stop
        self.setpoints = 0
        self.withheld = 0

    def velocity(self, v_ned: tuple[float, float, float], yaw_rate_rad_s: float) -> None:
        """One SET_POSITION_TARGET_LOCAL_NED to our vehicle, whatever the mode (the caller
        decides); nothing before an autopilot has been heard."""
        system = self.link.vehicle.system_id
        if system is None:
            self.withheld += 1
            return
        send = partial(
            _velocity_send,
            system=system,
            v_ned=v_ned,
            yaw_rate_rad_s=yaw_rate_rad_s,
        )
        if self.link.post(send, "SET_POSITION_TARGET_LOCAL_NED"):
            self.setpoints += 1

    def send_velocity(self, v_world_mps: tuple[float, float, float], yaw_rate_rad_s: float) -> None:
        if not self.allowed():
            self.withheld += 1
            return
        # world z up (NWU) to NED; a yaw rate about up is minus the rate about down
        vx, vy, vz = v_world_mps
        self.velocity((vx, -vy, -vz), -yaw_rate_rad_s)

    def send_stop(self) -> None:
        system = self.link.vehicle.system_id
        if not self.allowed() or system is None:
            self.withheld += 1
            return
        send = partial(_disarm_send, system=system, force=self.force_stop())
        self.link.post(send, "COMMAND_LONG")

    def send_land(self) -> bool:
        """Switch the vehicle to its autopilot's LAND (MAV_CMD_DO_SET_MODE: ArduCopter LAND,
        PX4 AUTO.LAND), which lands it on its own land detector; False where it cannot be
        asked (not ours to command, an unknown autopilot, the link down)."""
        system = self.link.vehicle.system_id
        mode = land_mode(self.link.vehicle)
        if not self.allowed() or system is None or mode is None:
            return False
        return self.link.post(partial(_land_send, system=system, mode=mode), "COMMAND_LONG")


class MavlinkPilot:
    """The perching pilot flying an ArduPilot or PX4 vehicle over ``url`` (a pymavlink
    connection string); call it once per camera frame, like ``PerchingPilot``.

    heartbeat_timeout_s : a vehicle silent this long is taken to have failed over to its own
    failsafe. odometry_max_age_s : LOCAL_POSITION_NED older than this is not used.
    proof_of_life_hz : the zero-velocity stream an armed PX4 vehicle gets while the pilot
    waits. target_system : the vehicle's MAVLink system id (None: the first autopilot heard).
    settings : the pilot's settings; by default those with ``on_senses_lost="release"`` (the
    autopilot's own modes fly a vehicle whose senses went stale); given settings are used as
    they are.
    link : an open ``MavlinkLink`` to use instead of opening ``url``.
    """

    def __init__(
        self,
        url: str,
        *,
        controller: PerchingController | None = None,
        settings: PilotSettings | None = None,
        heartbeat_timeout_s: float = 3.0,
        odometry_max_age_s: float = 0.5,
        proof_of_life_hz: float = 10.0,
        target_system: int | None = None,
        report: Callable[[str], None] | None = None,
        link: MavlinkLink | None = None,
    ) -> None:
        self.link = link or MavlinkLink(
            url,
            target_system=target_system,
            streams=("ATTITUDE", "LOCAL_POSITION_NED", "HIGHRES_IMU"),
            heartbeat_hz=HEARTBEAT_HZ,
            report=report or log.warning,
        )
        self.report = self.link.report
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.odometry_max_age_s = odometry_max_age_s
        self.proof_of_life_period_s = 1.0 / proof_of_life_hz
        self.commander = SetpointCommander(
            self.link, self.engaged, lambda: self.pilot.state == PilotState.PERCHED
        )
        self.pilot = PerchingPilot(
            self.commander,
            self.attitude,
            controller=controller,
            settings=settings or PilotSettings(on_senses_lost="release", command="velocity"),
            height_m=self.height_m,
            odometry=self.odometry,
            ages=self.ages,
            report=self.report,
            on_ground=lambda: self.vehicle.on_ground(time.monotonic()),
            specific_force=self.specific_force,
        )
        self.proof_of_life = 0
        self._next_proof = 0.0
        self._waiting_reported = False
        self.link.listeners.append(self._heard)
        self.link.pollers.append(self._poll)
        self.clock = PilotClock(self.pilot).start()

    # -- the vehicle, in the pilot's frames -------------------------------------------------

    @property
    def vehicle(self) -> VehicleState:
        return self.link.vehicle

    def attitude(self) -> Array:
        """``R_world_body`` (NWU from FLU) from the vehicle's ATTITUDE."""
        R_ned_frd = self.vehicle.R_ned_frd
        return np.eye(3) if R_ned_frd is None else F @ R_ned_frd @ F

    def odometry(self) -> tuple[Array, Array] | None:
        """Position and velocity in NWU from LOCAL_POSITION_NED, None if old or missing."""
        v = self.vehicle
        if v.p_ned_m is None or v.v_ned_mps is None or not self._fresh(v.position_t_s):
            return None
        return F @ v.p_ned_m, F @ v.v_ned_mps

    def specific_force(self) -> Array | None:
        """The accelerometer's specific force in FLU (m/s^2; at rest +g along z) from the
        vehicle's HIGHRES_IMU, None if old or missing."""
        v = self.vehicle
        if v.f_frd_mps2 is None or not self._fresh(v.imu_t_s):
            return None
        f_flu: Array = F @ v.f_frd_mps2
        return f_flu

    def ages(self) -> SenseAges:
        """How old the vehicle's ATTITUDE and LOCAL_POSITION_NED (the height's source) are."""
        now = time.monotonic()
        position_s = self.vehicle.position_age_s(now)
        return SenseAges(self.vehicle.attitude_age_s(now), position_s, position_s)

    def height_m(self) -> float | None:
        """Height above the local origin (``-z`` of LOCAL_POSITION_NED)."""
        motion = self.odometry()
        return None if motion is None else float(motion[0][2])

    def _fresh(self, t_s: float) -> bool:
        return time.monotonic() - t_s < self.odometry_max_age_s

    def alive(self) -> bool:
        return time.monotonic() - self.vehicle.heartbeat_t_s < self.heartbeat_timeout_s

    def engaged(self) -> bool:
        """The vehicle is alive, armed and in the mode that takes our setpoints."""
        return self.alive() and self.vehicle.armed and takes_setpoints(self.vehicle)

    def ready(self) -> bool:
        """``engaged``, with the attitude and odometry the controller needs."""
        return (
            self.engaged()
            and self.vehicle.R_ned_frd is not None
            and self._fresh(self.vehicle.attitude_t_s)
            and self.odometry() is not None
        )

    def missing(self) -> str:
        """What keeps the pilot from taking over, in words ('' when nothing does)."""
        v = self.vehicle
        if not self.alive():
            return "no HEARTBEAT from an autopilot"
        if not (v.armed and takes_setpoints(v)):
            mode = setpoint_mode(v) or "GUIDED or OFFBOARD"
            return f"the vehicle is not armed in {mode}"
        if not self.ready():
            return "no ATTITUDE and LOCAL_POSITION_NED streaming"
        return ""

    def summary(self) -> str:
        """One line: whether the pilot took over, what it sent and how it ended, or why it
        never took over."""
        taken = [t for t, before, _ in self.pilot.transitions if before == PilotState.WAITING]
        if not taken:
            why = self.missing() or "no target in view while the vehicle was ready"
            return f"MAVLink pilot: never took over ({why})"
        return (
            f"MAVLink pilot: took over at t = {taken[0]:.2f} s, sent "
            f"{self.commander.setpoints} setpoints, ended {self.pilot.state}"
        )

    def wait_until_ready(self, timeout_s: float, poll_s: float = 0.02) -> bool:
        """Wait up to ``timeout_s`` for ``ready``; say once what is missing if it is not."""
        deadline = time.monotonic() + timeout_s
        while not self.ready() and time.monotonic() < deadline:
            time.sleep(poll_s)
        if self.ready():
            return True
        missing = self.missing()
        self.report(
            f"MAVLink {self.link.url}: {missing} after {timeout_s:g} s; tracking starts, and "
            "the pilot takes over once it is ready"
        )
        self._waiting_reported = True
        return False

    # -- per frame, and on the link's thread ------------------------------------------------

    def __call__(self, estimate: Estimate | None, t_s: float) -> None:
        """The per-frame hook ``track`` calls: the pilot takes over only when ``ready``."""
        if self.pilot.state == PilotState.WAITING and not self.ready():
            if not self._waiting_reported and estimate is not None and estimate.valid:
                mode = setpoint_mode(self.vehicle) or "GUIDED (ArduPilot) or OFFBOARD (PX4)"
                self.report(
                    f"pilot: target in view, waiting for the vehicle to be armed in {mode} "
                    "with its attitude and local position streaming"
                )
                self._waiting_reported = True
            return
        self.pilot.update(estimate, t_s)

    def _heard(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "LOCAL_POSITION_NED":
            self.pilot.tick_now()
        elif kind == "HEARTBEAT" and self.pilot.flying:
            if not takes_setpoints(self.vehicle):
                mode = setpoint_mode(self.vehicle) or "the setpoint mode"
                self.pilot.release(
                    f"the vehicle left {mode} (custom mode {self.vehicle.custom_mode}): "
                    "the autopilot flies it now"
                )
            elif not self.vehicle.armed:
                self.pilot.release("the vehicle disarmed")

    def _poll(self, now: float) -> None:
        if self.pilot.flying and not self.alive():
            self.pilot.release(
                f"no HEARTBEAT from the vehicle for {self.heartbeat_timeout_s:g} s: its own "
                "failsafe takes over"
            )
        proof = (
            self.pilot.state == PilotState.WAITING
            and self.vehicle.autopilot == MAV_AUTOPILOT_PX4
            and self.alive()
            and self.vehicle.armed
        )
        if proof and now >= self._next_proof:
            self._next_proof = now + self.proof_of_life_period_s
            self.commander.velocity((0.0, 0.0, 0.0), 0.0)
            self.proof_of_life += 1

    def close(self, reason: str = "tracking ended") -> None:
        """Stop: one zero-velocity setpoint if flying in the setpoint mode (the autopilot's
        LAND if the pilot was landing), then nothing more (said once), and close the link.
        The last command and the release go out under the pilot's lock: no tick on the
        pilot's clock or the link's thread sends a setpoint after the last one."""
        self.clock.stop()
        with self.pilot.exclusive():
            if self.pilot.state == PilotState.LANDING and self.commander.send_land():
                self.pilot.release(
                    f"{reason} while landing: the autopilot's LAND lands the vehicle"
                )
            elif self.pilot.flying:
                mode = setpoint_mode(self.vehicle) or "its mode"
                if self.engaged():
                    self.commander.velocity((0.0, 0.0, 0.0), 0.0)
                    last = "a hover setpoint, then nothing more"
                else:
                    last = "nothing more sent (the vehicle does not take setpoints now)"
                self.pilot.release(
                    f"{reason}: {last}; the autopilot holds the vehicle in {mode} or its "
                    "failsafe acts"
                )
        self.report(self.summary())
        self.link.close()
