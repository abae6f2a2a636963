"""The vehicle links a track flies on: opened for the options given, closed (and a Crazyflie
landed) when the frames end, fail or are interrupted."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

from perchpose.target import TargetSpec
from perchpose.values import Estimate

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from perchpose.control import ControllerSettings, PerchingController
    from perchpose.control.time_offset import TimeOffset

MAVLINK_READY_WAIT_S = 3.0  # how long the MAVLink pilot waits for the vehicle before the frames

FrameHook = Callable[[Estimate | None, float], None]  # an estimate and its frame's time


@dataclass(frozen=True)
class LinkOptions:
    """Which links to open. mavlink_url : a pymavlink connection string (None: no MAVLink).
    mavlink_frame : LANDING_TARGET's frame (``body_frd`` or ``local_ned``). mavlink_pilot : fly
    the perching controller through velocity setpoints instead of sending LANDING_TARGET.
    target_relative, distance_sensor : also send TARGET_RELATIVE, DISTANCE_SENSOR.
    target_system : the autopilot's system id (None: the first heard). crazyflie_uri : a cflib
    URI (None: no Crazyflie). mount : ``up``, ``down`` or a mount YAML (None: upward).
    position_fixes : the flying pilot hands each fix to the vehicle's estimator where its link
    can (the Crazyflie's Kalman filter, as an external position). command : what the flying
    pilot sends (``PilotSettings.command``: ``velocity``, ``full-state`` or ``attitude``; None:
    each link's own, attitude setpoints to a Crazyflie and velocities to a MAVLink autopilot,
    which is sent velocities whatever is asked)."""

    mavlink_url: str | None = None
    mavlink_frame: str = "body_frd"
    mavlink_pilot: bool = False
    target_relative: bool = False
    distance_sensor: bool = False
    target_system: int | None = None
    crazyflie_uri: str | None = None
    mount: str | None = None
    position_fixes: bool = True
    command: str | None = None

    @property
    def flies(self) -> str | None:
        """The flag of a link that flies the vehicle (None: the links only inform it)."""
        if self.mavlink_url is not None and self.mavlink_pilot:
            return "--mavlink-pilot"
        return "--crazyflie" if self.crazyflie_uri is not None else None


@dataclass
class VehicleLinks:
    """The open links: ``hooks`` take each frame's estimate and time; ``controllers`` are the
    perching controllers of the links that fly the vehicle."""

    hooks: list[FrameHook] = field(default_factory=list)
    controllers: list[PerchingController] = field(default_factory=list)

    def time_offset(self) -> TimeOffset | None:
        """The flying controller's latest estimate of the camera-to-vehicle time offset
        (None: no link flies, or no estimate yet)."""
        for controller in self.controllers:
            if controller.time_offset is not None:
                return controller.time_offset
        return None

    def say_clock(self, report: Callable[[str], None]) -> None:
        """Say the flying controller's last time-offset estimate, and whether it placed the
        fixes (nothing when there is none)."""
        for controller in self.controllers:
            offset = controller.time_offset
            if offset is None:
                continue
            used = controller.capture_time_correction_s() != 0.0
            report(
                f"camera clock against the vehicle's, from the motion: {offset.describe()}; "
                + ("the fixes were placed by it" if used else "not used (too unsure, or not asked)")
            )
            return

    def say_fixes(self, report: Callable[[str], None]) -> None:
        """Say how many fixes the flying controller gave the vehicle's estimator (nothing
        when none)."""
        for controller in self.controllers:
            fixes = controller.position_fixes
            if fixes.sent or fixes.refused:
                report(
                    f"position fixes for the vehicle's estimator: {fixes.sent} made, "
                    f"{fixes.refused} held back as over {fixes.settings.max_jump_m:g} m aside from "
                    "its own estimate"
                )


def _flying_settings(o: LinkOptions) -> tuple[NDArray[np.float64] | None, ControllerSettings]:
    """The camera's mount (None: upward, the default) and the flying controller's settings;
    a flying link refuses a camera that does not look up."""
    from perchpose.control import ControllerSettings, mount_T_body_camera
    from perchpose.control.mount import require_upward
    from perchpose.control.position_fix import PositionFixSettings

    T_body_camera = mount_T_body_camera(o.mount) if o.mount else None
    if T_body_camera is not None:
        for flag, on in (("--mavlink-pilot", o.mavlink_pilot), ("--crazyflie", o.crazyflie_uri)):
            if on:
                require_upward(T_body_camera, flag)
    settings = ControllerSettings(position_fixes=PositionFixSettings(send=o.position_fixes))
    if T_body_camera is not None:
        settings = replace(settings, T_body_camera=T_body_camera)
    return T_body_camera, settings


@contextmanager
def vehicle_links(
    target: TargetSpec, options: LinkOptions, report: Callable[[str], None]
) -> Iterator[VehicleLinks]:
    """The links ``options`` asks for; at the end a Crazyflie is landed and every link
    closed, newest first."""
    from perchpose.control import PerchingController, PilotSettings
    from perchpose.control.pilot import PilotState
    from perchpose.control.pilot_clock import PilotClock
    from perchpose.control.pilot_settings import DEFAULT_COMMAND

    o = options
    T_body_camera, settings = _flying_settings(o)
    links = VehicleLinks()
    closers: list[Callable[[], None]] = []
    pilot = None
    try:
        if o.mavlink_url is not None and o.mavlink_pilot:
            from perchpose.io.mavlink.pilot import MavlinkPilot

            links.controllers.append(PerchingController(settings))
            autopilot = MavlinkPilot(
                o.mavlink_url,
                controller=links.controllers[-1],
                settings=PilotSettings(on_senses_lost="release", command=o.command or "velocity"),
                target_system=o.target_system,
                report=report,
            )
            closers.append(autopilot.close)
            links.hooks.append(autopilot)
            autopilot.wait_until_ready(MAVLINK_READY_WAIT_S)
        elif o.mavlink_url is not None:
            from perchpose.io.mavlink.landing_target_sink import LandingTargetSink

            sink = LandingTargetSink(
                o.mavlink_url,
                frame=o.mavlink_frame,
                T_body_camera=T_body_camera,
                target=target,
                target_relative=o.target_relative,
                distance_sensor=o.distance_sensor,
                target_system=o.target_system,
                report=report,
            )
            closers.append(sink.close)
            links.hooks.append(sink)
        if o.crazyflie_uri is not None:
            from perchpose.io.crazyflie import connect

            # cflib logs its connection failures with tracebacks; the link's error says it once
            logging.getLogger("cflib").addHandler(logging.NullHandler())
            link = connect(o.crazyflie_uri, report=report)
            closers.append(link.close)
            links.controllers.append(PerchingController(settings))
            pilot = link.pilot(
                controller=links.controllers[-1],
                settings=PilotSettings(command=o.command or DEFAULT_COMMAND),
            )
            links.hooks.append(pilot)
            clock = PilotClock(pilot).start()  # the pilot's watchdogs tick without frames
            closers.append(clock.stop)
        try:
            yield links
        finally:
            links.say_clock(report)
            links.say_fixes(report)
            if pilot is not None:  # source ended, an error, or Ctrl-C: land
                pilot.abort(pilot.now() or pilot.last_t_s, "tracking ended")
                if pilot.state == PilotState.LANDING:
                    report(
                        "landing until touchdown is sensed; Ctrl-C again stops the pilot, and "
                        "the Crazyflie's watchdog then cuts the motors wherever it is"
                    )
                pilot.land()
    finally:
        for close in reversed(closers):
            close()
