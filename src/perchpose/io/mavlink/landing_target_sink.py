"""Sending the estimate to PX4 or ArduPilot as MAVLink LANDING_TARGET messages.

Needs the ``mavlink`` extra (``pip install perchpose[mavlink]``). One ``LandingTargetSink``
owns one ``perchpose.io.mavlink.link.MavlinkLink``, whose thread sends the LANDING_TARGET
messages ``send`` queues, the HEARTBEAT and TIMESYNC (once answered, ``time_usec`` is the
frame's grab time on the autopilot's clock), reads the vehicle's ATTITUDE and
LOCAL_POSITION_NED (needed for ``frame="local_ned"``) and reopens a link that failed, so
tracking never waits on the network. Estimates arriving while the link is down are dropped,
and tracking goes on.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from perchpose.control.mount import default_T_body_camera
from perchpose.errors import LinkError
from perchpose.geometry import check_transform
from perchpose.io.mavlink.landing_target import (
    FRAMES,
    DistanceReading,
    LandingTarget,
    check_line_of_sight,
    distance_reading,
    landing_target,
)
from perchpose.io.mavlink.link import (
    MAV_COMP_ID_ONBOARD_COMPUTER,
    MavlinkLink,
    VehicleState,
    check_url,
    mavutil_module,
)
from perchpose.io.mavlink.target_relative import dialect, target_relative, target_relative_send
from perchpose.io.mavlink.timesync import TimeSync
from perchpose.target import TargetSpec
from perchpose.values import Estimate

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

__all__ = ["LandingTargetSink", "check_url", "mavutil_module"]

# MAVLink enum values (common.xml); kept here so that the module imports without pymavlink
MAV_FRAME_IDS = {"local_ned": 1, "body_frd": 12}
LANDING_TARGET_TYPE_VISION_FIDUCIAL = 2


DISTANCE_MAX_CM = 500  # the large marker is read to about 5 m (DESIGN 3b)
DISTANCE_MIN_CM = 5
MAV_DISTANCE_SENSOR_UNKNOWN = 4


def _distance_send(mav: Any, *, reading: DistanceReading) -> None:
    mav.distance_sensor_send(
        int(time.monotonic() * 1000) & 0xFFFFFFFF,
        DISTANCE_MIN_CM,
        DISTANCE_MAX_CM,
        reading.current_cm,
        MAV_DISTANCE_SENSOR_UNKNOWN,
        MAV_COMP_ID_ONBOARD_COMPUTER,  # the sensor's id: one per sender
        reading.orientation,
        reading.covariance_cm2,
    )


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


class LandingTargetSink:
    """Sends one LANDING_TARGET per valid estimate over a pymavlink connection.

    url : pymavlink connection string. frame : ``body_frd`` (ArduPilot) or ``local_ned`` (PX4).
    T_body_camera : the camera's mounting on the body (FLU), default
    ``control.default_T_body_camera()``. target : sets the angular size fields.
    time_offset_s : added to the frame times for ``time_usec`` until TIMESYNC has mapped this
    computer's clock to the autopilot's (or for estimates without ``grabbed_s``); then
    ``time_usec`` is ``Estimate.captured_s`` (the frame's date less the camera's latency) on the
    autopilot's clock. timesync_period_s : how
    often a TIMESYNC request is sent (0: never; requests from the vehicle are answered all the
    same). attitude_max_age_s, position_max_age_s : the vehicle's ATTITUDE and
    LOCAL_POSITION_NED older than this are not used (``local_ned`` estimates wait for a fresh
    attitude). target_system : the vehicle's MAVLink system id (None: the first autopilot
    heard); nothing from another system is used. max_age_s : an estimate older than this is
    not sent: the age of its newest measurement (``Estimate.age_s``) plus, for a live frame,
    the time since its frame was captured (a frame that waited on the estimator, a compile or
    the link is as old as that when it would arrive); default 0.5 s, well
    inside the autopilots' own LANDING_TARGET timeouts (ArduPilot 2 s, PX4 ``PLD_BTOUT`` 5 s).
    target_relative : also send TARGET_RELATIVE (PX4's vision target estimator;
    ``perchpose.io.mavlink.target_relative``) with each LANDING_TARGET, in the same frame, with the
    covariance's standard deviations (estimates without a covariance send LANDING_TARGET only,
    reported once). distance_sensor : also send DISTANCE_SENSOR, the target's distance along
    the body's vertical axis, for a vehicle without a rangefinder (a camera looking up or
    down only). report : receives the one-line link reports (default: the
    ``perchpose.io.mavlink.landing_target_sink`` logger).
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
        attitude_max_age_s: float = 0.5,
        max_age_s: float = 0.5,
        target_relative: bool = False,
        distance_sensor: bool = False,
        target_system: int | None = None,
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
        self.time_offset_s = time_offset_s
        self.position_max_age_s = position_max_age_s
        self.attitude_max_age_s = attitude_max_age_s
        if not max_age_s > 0:
            raise LinkError(f"max_age_s must be positive, got {max_age_s}")
        self.max_age_s = max_age_s
        self.refused = 0
        self._refused_reported = False
        self.target_relative = target_relative
        self.distance_sensor = distance_sensor
        self._relative_reported = False
        if target_relative:
            dialect()  # generated now: a broken pymavlink fails here, not on the first frame
        self.link = MavlinkLink(
            self.url,
            source_system=source_system,
            source_component=source_component,
            heartbeat_period_s=heartbeat_period_s,
            timesync_period_s=timesync_period_s,
            retry_period_s=retry_period_s,
            target_system=target_system,
            streams=("ATTITUDE", "LOCAL_POSITION_NED") if frame == "local_ned" else (),
            report=report or log.warning,
        )
        self.report = self.link.report

    # -- the link -------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        return self.link.connected

    @property
    def vehicle(self) -> VehicleState:
        return self.link.vehicle

    @property
    def timesync(self) -> TimeSync:
        return self.link.timesync

    @property
    def sent(self) -> int:
        """LANDING_TARGET messages sent."""
        return self.link.sent

    @property
    def dropped(self) -> int:
        """LANDING_TARGET messages dropped (the link was down or far behind)."""
        return self.link.dropped

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
        since_capture_s = 0.0
        if math.isfinite(estimate.captured_s):
            since_capture_s = max(0.0, time.monotonic() - estimate.captured_s)
        age_s = estimate.age_s + since_capture_s
        if not age_s <= self.max_age_s:
            self._refuse(
                f"estimate at t = {estimate.t_s:.3f} s is {age_s:.2f} s old "
                f"(limit {self.max_age_s:g} s); not sent"
            )
            return None
        if not estimate.t_s + self.time_offset_s >= 0.0:
            self._refuse(f"estimate at t = {estimate.t_s:.3f} s is before time zero; not sent")
            return None
        R_ned_frd = p_ned = None
        if self.frame == "local_ned":
            R_ned_frd = self._attitude()
            if R_ned_frd is None:
                return None
            age = self.vehicle.position_age_s(time.monotonic())
            if age < self.position_max_age_s:
                p_ned = self.vehicle.p_ned_m
        shifted = replace(estimate, t_s=estimate.t_s + self.time_offset_s)
        time_usec = None
        if math.isfinite(estimate.captured_s):
            time_usec = self.timesync.remote_usec(estimate.captured_s)
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

    def _fresh_attitude(self) -> Array | None:
        """The attitude if younger than ``attitude_max_age_s``, else None."""
        age = self.vehicle.attitude_age_s(time.monotonic())
        return self.vehicle.R_ned_frd if age < self.attitude_max_age_s else None

    def _attitude(self) -> Array | None:
        """``_fresh_attitude``, saying once why there is none: a local_ned estimate is never
        turned by an old attitude."""
        R_ned_frd = self._fresh_attitude()
        if R_ned_frd is None:
            age = self.vehicle.attitude_age_s(time.monotonic())
            why = (
                "no ATTITUDE from the vehicle yet"
                if math.isinf(age)
                else f"the vehicle's ATTITUDE is {age:.1f} s old "
                f"(limit {self.attitude_max_age_s:g} s)"
            )
            self.link.say_once(
                f"attitude {math.isinf(age)}",
                f"MAVLink {self.url}: {why}; local_ned estimates are held back until it is fresh",
            )
        return R_ned_frd

    def send(self, estimate: Estimate | None) -> bool:
        """Hand LANDING_TARGET for a valid estimate to the link's thread; True if it was
        accepted (False: nothing to send, or the link is down and the estimate is dropped).
        Never waits on the network."""
        if estimate is None:
            return False
        msg = self.message(estimate)
        if msg is None:
            return False
        posted = self.link.post(partial(_landing_target_send, msg=msg), "LANDING_TARGET")
        if posted and self.target_relative:
            self._send_relative(estimate, msg.time_usec)
        if posted and self.distance_sensor:
            reading = distance_reading(estimate, self.T_body_camera, DISTANCE_MAX_CM)
            if reading is not None:
                self.link.post(partial(_distance_send, reading=reading), "DISTANCE_SENSOR")
        return posted

    def _send_relative(self, estimate: Estimate, time_usec: int) -> None:
        try:
            relative = target_relative(
                estimate,
                self.T_body_camera,
                frame=self.frame,
                R_ned_frd=self._attitude() if self.frame == "local_ned" else self._fresh_attitude(),
                timestamp_usec=time_usec,
            )
        except LinkError as exc:
            if not self._relative_reported:
                self.report(f"MAVLink {self.url}: {exc} (reported once)")
                self._relative_reported = True
            return
        self.link.post(partial(target_relative_send, msg=relative), "TARGET_RELATIVE")

    def __call__(self, estimate: Estimate | None, t_s: float) -> None:
        """The per-frame hook ``track`` calls."""
        self.send(estimate)

    def close(self) -> None:
        """Send what is queued, stop the link's thread and close the connection; say how many
        messages never went out, if any."""
        self.link.close()
        if self.dropped:
            self.report(
                f"MAVLink {self.url}: {self.dropped} of {self.sent + self.dropped} messages "
                "dropped unsent (the link was down, or fell behind frames read faster than it "
                "sends)"
            )

    def __enter__(self) -> LandingTargetSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
