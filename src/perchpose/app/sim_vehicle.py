"""``perchpose sim-vehicle``: the simulated drone of ``perch`` as a vehicle to try the links
on: it flies in real time in wind under the perching plate, speaks MAVLink as ArduCopter or
PX4 does (``perchpose.sim.autopilot``, ``perchpose.io.mavlink.vehicle_endpoint``) and streams
its upward camera as H.264 over UDP (``perchpose.io.video_stream``), so that
``perchpose track <its stream> --mavlink <its link> --mavlink-pilot`` perches it end to end,
each in its own process.

The world is ``perch``'s: the same vehicle model and onboard velocity loop, Dryden wind, the
same renderer, camera, target, mount and plate, and the same contact rules; it starts
hovering armed in its hold mode, 0.6-1.5 m under the plate, and an operator's switch puts it
in GUIDED or OFFBOARD ``hand_over_s`` after the start (PX4: once the companion's setpoints
stream). The plate stops what touches it (an inelastic ceiling); a touch that the contact
rules call a perch seats the magnet, which then holds the vehicle whatever its motors do.
A vehicle disarmed in the air falls.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from perchpose.app.inputs import load_camera, load_target
from perchpose.errors import LinkError, VehicleConfigError
from perchpose.geometry import invert_transform, make_transform
from perchpose.io.mavlink.vehicle_endpoint import (
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_DENIED,
    MAV_RESULT_UNSUPPORTED,
    F,
    VehicleEndpoint,
)
from perchpose.io.video_stream import H264Stream
from perchpose.sim.autopilot import MAV_AUTOPILOT, SETPOINT_MODE, StandInAutopilot
from perchpose.sim.contact import Contact, PlateContact
from perchpose.sim.disturbances import OdometryModel
from perchpose.sim.perch import REST_Z_M, PerchSetup, draw_start, set_on_floor
from perchpose.sim.quadrotor import Quadrotor
from perchpose.sim.wind import DrydenWind

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

BLOCK_S = 0.01  # the world advances in blocks this long between looks at the link
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_DO_SET_MODE = 176
FORCE_DISARM = 21196.0
MAV_FRAME_LOCAL_NED = 1
POSITION_IGNORED, VELOCITY_IGNORED, YAW_RATE_IGNORED = 0b111, 0b111000, 2048


@dataclass(frozen=True)
class SimVehicleOptions:
    """``perchpose sim-vehicle``'s options (see the command's help)."""

    mavlink: str = "udpin:127.0.0.1:14550"
    video: str = "udp://127.0.0.1:5600"
    autopilot: str = "ardupilot"
    wind: str = "light"
    seed: int = 0
    hand_over_s: float | None = 2.0
    duration_s: float | None = None
    fps: float = 30.0
    camera_file: str = "preset:fpv"
    target_file: str | None = None


@dataclass
class Outcome:
    """How the flight went: the first contact with the plate and its verdict, whether the
    magnet seated, where the motors stopped, a crash."""

    contact: Contact | None = None
    verdict: str = ""
    seated: bool = False
    motor_stop_height_m: float = math.nan
    crashed: bool = False
    events: list[str] = field(default_factory=list)


class SimulatedVehicle:
    """The world of a ``perch`` run with a stand-in autopilot in place of the pilot, advanced
    by ``advance_to``; frames come out through ``frame`` (index, gray image)."""

    def __init__(
        self,
        setup: PerchSetup,
        seed: int,
        autopilot: str,
        hand_over_s: float | None,
        frame: Callable[[int, NDArray[np.uint8]], None],
        report: Callable[[str], None] = log.info,
    ) -> None:
        self.setup = setup
        self.report = report
        self.frame = frame
        self.hand_over_s = hand_over_s
        world = np.random.default_rng(seed)
        start, yaw = draw_start(setup, world)
        below = setup.plate_z_m - float(start[2])
        self.vehicle = Quadrotor.hovering(setup.vehicle, start, yaw, setup.onboard)
        self.vehicle.ceiling_z_m = setup.plate_z_m if setup.ceiling_effect else None
        direction = float(world.uniform(-math.pi, math.pi))
        self.wind = DrydenWind(setup.wind_level, 1.0 / setup.fps, world, direction, setup.plate_z_m)
        self.odometry = OdometryModel(setup.disturbances, start, world)
        self.camera_rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(1)[0])
        self.renderer = setup.renderer()
        self.plate = PlateContact(setup.plate_z_m, setup.controller.p_body_magnet_m, setup.contact)
        self.autopilot = StandInAutopilot(autopilot, start)
        self.outcome = Outcome()
        self.t_s = 0.0
        self.frames = 0
        self.resting = False
        self._said = 0  # autopilot events already reported
        self._hand_over_refusal = ""
        self.report(
            f"sim-vehicle: {autopilot}, hovering {below:.2f} m under the plate "
            f"({start[0]:+.2f}, {start[1]:+.2f}) m, heading {math.degrees(yaw):.0f} deg, "
            f"wind {setup.wind} blowing to {math.degrees(direction):.0f} deg"
        )

    @property
    def on_ground(self) -> bool:
        return self.resting

    @property
    def height_m(self) -> float:
        return float(self.vehicle.p_m[2]) - REST_Z_M

    def say(self, line: str) -> None:
        self.outcome.events.append(f"{self.t_s:7.2f} s  {line}")
        self.report(f"sim-vehicle {self.t_s:7.2f} s: {line}")

    def _said_by_autopilot(self) -> None:
        events = self.autopilot.events
        for line in events[self._said :]:
            self.say(line)
        self._said = len(events)

    # -- the link's commands ----------------------------------------------------------

    def setpoint(self, msg: Any) -> str:
        """A SET_POSITION_TARGET_LOCAL_NED: '' when taken, else why not."""
        if int(msg.coordinate_frame) != MAV_FRAME_LOCAL_NED:
            return f"frame {msg.coordinate_frame}: only MAV_FRAME_LOCAL_NED (1) is flown"
        mask = int(msg.type_mask)
        yaw_rate = 0.0 if mask & YAW_RATE_IGNORED else -float(msg.yaw_rate)
        if not mask & POSITION_IGNORED:
            p = F @ np.array([msg.x, msg.y, msg.z], np.float64)
            taken = self.autopilot.position_setpoint(p, yaw_rate, self.t_s)
        elif not mask & VELOCITY_IGNORED:
            v = F @ np.array([msg.vx, msg.vy, msg.vz], np.float64)
            taken = self.autopilot.setpoint(v, yaw_rate, self.t_s)
        else:
            return "neither position nor velocity used (type mask)"
        self._said_by_autopilot()
        return "" if taken else "not in a setpoint mode"

    def command(self, msg: Any) -> tuple[int, int]:
        """A COMMAND_LONG: (command, MAV_RESULT)."""
        command = int(msg.command)
        why = ""
        if command == MAV_CMD_COMPONENT_ARM_DISARM and msg.param1 == 0:
            why = self.autopilot.disarm(msg.param2 == FORCE_DISARM, self.on_ground)
            if not why:
                self._motors_stopped()
        elif command == MAV_CMD_COMPONENT_ARM_DISARM:
            why = self.autopilot.arm(self.on_ground, self.vehicle.p_m)
        elif command == MAV_CMD_DO_SET_MODE:
            why = self.autopilot.set_mode(
                int(msg.param2), self.t_s, self.odometry.p_m, "asked over the link"
            )
        else:
            return command, MAV_RESULT_UNSUPPORTED
        if why:
            self.say(f"command {command} refused: {why}")
        self._said_by_autopilot()
        return command, MAV_RESULT_DENIED if why else MAV_RESULT_ACCEPTED

    def _motors_stopped(self) -> None:
        if math.isnan(self.outcome.motor_stop_height_m):
            held = self.outcome.seated or self.resting
            self.outcome.motor_stop_height_m = 0.0 if held else self.height_m

    # -- the world ---------------------------------------------------------------------

    def _hand_over(self) -> None:
        """The operator's switch to the setpoint mode, once it is time."""
        ap = self.autopilot
        if self.hand_over_s is None or self.t_s < self.hand_over_s or not ap.armed:
            return
        if ap.kind_of_mode != "hold":
            return
        name = SETPOINT_MODE[ap.kind]
        number = ap.modes[name]
        why = ap.set_mode(number, self.t_s, self.odometry.p_m, "the operator's switch")
        if why and why != self._hand_over_refusal:
            self.say(f"switch to {name} refused: {why}")
        self._hand_over_refusal = why
        if not why:
            self.hand_over_s = None
        self._said_by_autopilot()

    def advance_to(self, t_s: float) -> None:
        """The world through every block that ends by ``t_s``."""
        while self.t_s + BLOCK_S <= t_s + 1e-9:
            self._block()

    def _block(self) -> None:
        s = self.setup
        if self.t_s * s.fps >= self.frames - 1e-9:
            self.vehicle.wind_mps = self.wind.step()
            self._capture()
        self._hand_over()
        v_sp, yaw_rate = self.autopilot.command(self.t_s, self.odometry.p_m, self.on_ground)
        self._said_by_autopilot()
        if not self.autopilot.armed:
            self._motors_stopped()
        self._fly(v_sp, yaw_rate)
        self.t_s += BLOCK_S

    def _capture(self) -> None:
        s = self.setup
        v = self.vehicle
        T_world_camera = make_transform(v.R_world_body, v.p_m) @ s.controller.T_body_camera
        T_camera_target = invert_transform(T_world_camera) @ s.T_world_target
        self.frame(self.frames, self.renderer.render(T_camera_target, s.quality, self.camera_rng))
        self.frames += 1

    def _fly(self, v_sp: Array, yaw_rate: float) -> None:
        v = self.vehicle
        steps = round(BLOCK_S * self.setup.physics_hz)
        if self.outcome.seated or self.outcome.crashed:
            return  # the magnet holds it, or it lies where it fell
        if self.resting and not (self.autopilot.armed and v_sp[2] > 0.0):
            return
        self.resting = False
        v.thrust_scale = (1.0,) * 4 if self.autopilot.armed else (0.0,) * 4
        touched = v.fly(
            1.0 / self.setup.physics_hz,
            steps,
            v_sp,
            yaw_rate,
            self.odometry.v_mps,
            touched=self._touched,
        )
        if touched is not None:
            self._touch()
        self.odometry.update(v.p_m, v.v_mps, BLOCK_S, v.R_world_body, v.omega_rad_s)

    def _touched(self, vehicle: Quadrotor) -> bool:
        return self.plate(vehicle) or (vehicle.p_m[2] <= REST_Z_M and vehicle.v_mps[2] < 0.0)

    def _touch(self) -> None:
        v = self.vehicle
        contact = self.plate.contact
        if v.p_m[2] <= REST_Z_M:  # the floor
            hard = not set_on_floor(v)
            self.resting = True
            if hard:
                self.outcome.crashed = True
                self.autopilot.armed = False
                self.say("crashed into the floor")
            else:
                self.say("on the ground")
            return
        if contact is None:
            return
        self.plate.contact = None
        if self.outcome.contact is None:
            self.outcome.contact = contact
            self.outcome.verdict = contact.verdict(self.setup.contact)
            self.say(
                f"touched the plate with its {contact.part}: {self.outcome.verdict} "
                f"(offset {contact.offset_mm:.1f} mm, {contact.speed_mps:.2f} m/s, "
                f"tilt {contact.tilt_deg:.1f} deg)"
            )
            if self.outcome.verdict == "perched":
                self.outcome.seated = True
                self.say("the magnet seated: it holds the vehicle")
                return
        # the plate stops it: no further up, no speed into it
        v.p_m = v.p_m - np.array([0.0, 0.0, 0.002])
        vel = v.v_mps
        v.v_mps = np.array([vel[0], vel[1], min(0.0, float(vel[2]))])


def sim_setup(options: SimVehicleOptions) -> PerchSetup:
    """The ``perch`` setup the vehicle flies in: its camera, target, wind and frame rate."""
    setup = PerchSetup(load_camera(options.camera_file), load_target(options.target_file))
    return replace(setup, wind=options.wind).with_timing(options.fps, 1)


def _obey(
    world: SimulatedVehicle, endpoint: VehicleEndpoint, msg: Any, refused: Counter[str]
) -> None:
    """One message from the companion, addressed to this vehicle (or to every system)."""
    kind = msg.get_type()
    if kind not in ("SET_POSITION_TARGET_LOCAL_NED", "COMMAND_LONG"):
        return
    if int(msg.target_system) not in (0, endpoint.system_id):
        return
    if kind == "COMMAND_LONG":
        endpoint.ack(*world.command(msg))
        return
    why = world.setpoint(msg)
    if why:
        if not refused[why]:
            world.say(f"setpoint not flown: {why}")
        refused[why] += 1


def _fly_in_real_time(
    world: SimulatedVehicle,
    endpoint: VehicleEndpoint,
    duration_s: float | None,
    refused: Counter[str],
) -> None:
    start_s = time.monotonic()
    ap = world.autopilot
    said = (ap.custom_mode, ap.armed)
    while duration_s is None or world.t_s < duration_s:
        for msg in endpoint.messages():
            _obey(world, endpoint, msg, refused)
        world.advance_to(time.monotonic() - start_s)
        now = (ap.custom_mode, ap.armed)
        endpoint.heartbeat(world.t_s, *now, at_once=now != said)
        said = now
        v = world.vehicle
        endpoint.state(
            world.t_s,
            v.R_estimate,
            v.omega_rad_s,
            world.odometry.p_m,
            world.odometry.v_mps,
            world.on_ground,
            v.specific_force_body_mps2,
        )
        time.sleep(max(0.0, start_s + world.t_s + BLOCK_S - time.monotonic()))


def summary(
    world: SimulatedVehicle,
    endpoint: VehicleEndpoint,
    stream: H264Stream,
    refused: Counter[str],
) -> str:
    """What the flight came to and what each side sent, in a few lines."""
    o = world.outcome
    if o.seated:
        end = "perched: the magnet seated and holds it"
    elif o.crashed:
        end = "crashed"
    elif world.resting:
        end = "on the ground"
    else:
        end = f"in the air, {world.height_m:.2f} m up"
    if o.contact is not None and not o.seated:
        end += f" (it touched the plate: {o.verdict})"
    stop = o.motor_stop_height_m
    motors = "running" if math.isnan(stop) else f"stopped {stop:.2f} m above what it rests on"
    got = endpoint.received
    heard = (
        "nothing heard from a companion"
        if not endpoint.peer
        else (
            f"{got['SET_POSITION_TARGET_LOCAL_NED']} setpoints received "
            f"({world.autopilot.setpoints} flown, {sum(refused.values())} not), "
            f"{endpoint.landing_targets} LANDING_TARGET, {got['COMMAND_LONG']} commands, "
            f"{got['HEARTBEAT']} heartbeats"
        )
    )
    lines = [
        f"sim-vehicle after {world.t_s:.1f} s: {end}; motors {motors}; "
        f"mode {world.autopilot.mode}, {'armed' if world.autopilot.armed else 'disarmed'}",
        f"  link {endpoint.url}: {heard}",
        f"  video {stream.url}: {stream.sent} frames sent, {stream.dropped} dropped"
        + (f", stopped: {stream.error}" if stream.error else ""),
    ]
    return "\n".join(lines)


def serve(options: SimVehicleOptions, report: Callable[[str], None]) -> None:
    """Fly the vehicle in real time until ``duration_s`` (None: until interrupted), serving
    its MAVLink link and its video stream; its summary goes to ``report`` at the end, also
    when interrupted."""
    if options.autopilot not in MAV_AUTOPILOT:
        raise VehicleConfigError(
            f"unknown autopilot {options.autopilot!r} (choose {', '.join(MAV_AUTOPILOT)})"
        )
    if not (math.isfinite(options.fps) and options.fps > 0):
        raise VehicleConfigError(f"--fps must be a positive frame rate, got {options.fps}")
    setup = sim_setup(options)
    size = (setup.camera.width_px, setup.camera.height_px)
    stream = H264Stream(options.video, options.fps, size)
    try:
        endpoint = VehicleEndpoint(options.mavlink, MAV_AUTOPILOT[options.autopilot])
    except LinkError:
        stream.close()
        raise
    refused: Counter[str] = Counter()
    world = SimulatedVehicle(
        setup, options.seed, options.autopilot, options.hand_over_s, stream.send, report
    )
    try:
        _fly_in_real_time(world, endpoint, options.duration_s, refused)
    finally:
        stream.close()
        endpoint.close()
        report(summary(world, endpoint, stream, refused))
