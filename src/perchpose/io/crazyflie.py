"""The Crazyflie link: a cflib connection that streams the vehicle's attitude and height from
its state estimate, and hands out the perching pilot (``perchpose.control.pilot``) wired to it.

Only ``connect`` imports cflib; ``CflibCommander`` turns the pilot's SI setpoints into calls
on any object with cflib's ``Commander`` methods (tests use a real
``cflib.crazyflie.Crazyflie`` over a fake link).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from perchpose.control.gyro import GyroAttitude, GyroReading
from perchpose.control.lean import CRAZYFLIE_KALMAN_LAG_S
from perchpose.control.pilot import PerchingPilot, PilotSettings, SenseAges
from perchpose.errors import LinkError
from perchpose.geometry import roll_pitch_rad, rotation_from_quaternion, yaw_rad
from perchpose.io.samples import SampleGate

Array = NDArray[np.float64]
GRAVITY_MPS2 = 9.81  # the firmware's g: its ``acc`` log group is in g
VELOCITY_GAINS = ("velCtlPid.vxKp", "velCtlPid.vyKp")  # the firmware's, deg per m/s
ESTIMATOR_PARAM = "stabilizer.estimator"  # 0 the firmware's choice, 1 complementary, 2 Kalman
COMPLEMENTARY_ESTIMATOR, KALMAN_ESTIMATOR = 1, 2
# the thrust the firmware's PID hovers on before its integral (``posCtlPid.thrustBase``), in
# the motors' units: the hover a level-thrust setpoint's fraction is of
HOVER_THRUST = 36000
log = logging.getLogger(__name__)


def velocity_kp_deg(gain_per_s: float) -> float:
    """``velCtlPid.vxKp`` (degrees of tilt per m/s of error) for a horizontal velocity-loop
    gain: g tan(kp) per m/s, so for small tilts kp = gain / g in radians (25 is about 4.3 /s)."""
    return math.degrees(gain_per_s / GRAVITY_MPS2)


class CflibCommander:
    """The pilot's ``VehicleCommander`` on cflib's ``Commander``: a velocity in the world
    frame of the Crazyflie's state estimator (z up, m/s) with the yaw rate in deg/s
    (``send_velocity_world_setpoint``), a full state (``send_full_state_setpoint``: the
    position the firmware's position loop holds on its own estimate), or an attitude
    (``send_zdistance_setpoint``: a roll, a pitch, the yaw rate and the height); a stop cuts
    the motors and hands the setpoint priority back to the high-level commander
    (``send_stop_setpoint``, ``send_notify_setpoint_stop``). A level thrust (cflib's legacy
    ``send_setpoint``: level, no yaw rate, a fraction of ``hover_thrust``) tries the magnet's
    hold before a stop (``control.seat_check``).
    With cflib's ``Extpos`` (``extpos``) it hands the Kalman filter the camera's fixes as an
    external position.

    With cflib's ``Param`` (``param``) it sets the firmware's horizontal velocity gains
    (``velCtlPid.vxKp``, ``vyKp``: degrees of tilt per m/s of error; g tan(kp) per m/s is the
    loop's gain, so 25 is about 4.3 /s) and gives back the values it read before."""

    def __init__(
        self,
        commander: Any,
        param: Any = None,
        own_gains: dict[str, str] | None = None,
        extpos: Any = None,
        hover_thrust: int = HOVER_THRUST,
    ) -> None:
        self.commander = commander
        self.hover_thrust = hover_thrust
        self._thrust_unlocked = False
        self.extpos = extpos
        self.param = param
        self.own_gains = own_gains or {}  # the vehicle's velocity gains, read at connection

    def set_velocity_gain(self, gain_per_s: float) -> bool:
        """False without the vehicle's own gains to give back (read at connection)."""
        if self.param is None or set(self.own_gains) != set(VELOCITY_GAINS):
            return False
        kp_deg = velocity_kp_deg(gain_per_s)
        try:
            for name in VELOCITY_GAINS:
                self.param.set_value(name, f"{kp_deg:.3f}")
        except Exception:  # cflib raises bare Exceptions (no such parameter, not connected)
            self.restore_velocity_gain()
            return False
        return True

    def restore_velocity_gain(self) -> None:
        try:
            for name, value in self.own_gains.items():
                self.param.set_value(name, value)
        except Exception:  # the link is going: the vehicle keeps ours until it restarts
            return

    def send_velocity(self, v_world_mps: tuple[float, float, float], yaw_rate_rad_s: float) -> None:
        vx, vy, vz = v_world_mps
        self.commander.send_velocity_world_setpoint(vx, vy, vz, math.degrees(yaw_rate_rad_s))

    def send_full_state(
        self,
        p_world_m: tuple[float, float, float],
        v_world_mps: tuple[float, float, float],
        yaw_rad: float,
        yaw_rate_rad_s: float,
    ) -> None:
        """``send_full_state_setpoint``: the position and velocity, no acceleration, the yaw
        as the orientation's quaternion (about up), and no body rates: the yaw is in the
        orientation, and the rates' units are not settled (cflib says deg/s and packs them
        times 1000; the firmware's decoder reads mrad/s), so ``yaw_rate_rad_s`` is not sent."""
        orientation = (0.0, 0.0, math.sin(yaw_rad / 2.0), math.cos(yaw_rad / 2.0))
        self.commander.send_full_state_setpoint(
            p_world_m, v_world_mps, (0.0, 0.0, 0.0), orientation, 0.0, 0.0, 0.0
        )

    def send_attitude(
        self, roll_rad: float, pitch_rad: float, yaw_rate_rad_s: float, z_m: float
    ) -> None:
        """``send_zdistance_setpoint``: roll and pitch in degrees, the yaw rate in deg/s and
        the height (m) its position loop holds on its own estimate. The commander's decoder
        passes roll and pitch on as they come, so the pitch goes in the firmware's legacy
        sign (positive nose up, the sign its PID compares with its own attitude's). The yaw
        rate is counter-clockwise positive, as for ``send_velocity_world_setpoint``: cflib
        turns it round for a firmware that still takes the legacy packet."""
        self.commander.send_zdistance_setpoint(
            math.degrees(roll_rad), -math.degrees(pitch_rad), math.degrees(yaw_rate_rad_s), z_m
        )

    def send_level_thrust(self, hover_fraction: float) -> None:
        """``send_setpoint``: level, no yaw rate, ``hover_fraction`` of ``hover_thrust`` (the
        motors' units; the firmware's PID passes it on with its height loop off). The
        firmware takes no thrust on this packet until one with none unlocks it: the first call
        sends that one first (the motors ease for the moment between the two packets, which
        is what the call asks of them anyway)."""
        if not self._thrust_unlocked:
            self.commander.send_setpoint(0.0, 0.0, 0.0, 0)
            self._thrust_unlocked = True
        thrust = round(min(1.0, max(0.0, hover_fraction)) * self.hover_thrust)
        self.commander.send_setpoint(0.0, 0.0, 0.0, min(thrust, 0xFFFF))

    def send_stop(self) -> None:
        self.commander.send_stop_setpoint()
        self.commander.send_notify_setpoint_stop(0)

    def send_land(self) -> bool:
        """The Crazyflie's low-level setpoints have no landing of their own to hand over to."""
        return False

    def send_position_fix(self, p_world_m: tuple[float, float, float]) -> bool:
        """The camera's fix to the Crazyflie's Kalman filter as an external position
        (``send_extpos``, fused with ``locSrv.extPosStdDev``); False without cflib's
        ``Extpos``."""
        if self.extpos is None:
            return False
        x, y, z = p_world_m
        self.extpos.send_extpos(x, y, z)
        return True


class CrazyflieConnection:
    """An open cflib link with the vehicle's attitude, height, position and velocity streamed
    from its state estimate (``stateEstimate.qw/qx/qy/qz`` and ``.z`` with the gyro's
    ``gyro.x/y/z`` (deg/s, half floats) in one log block, ``stateEstimate.x/y/vx/vy/vz`` with
    the accelerometer's ``acc.x/y/z`` (g, half floats) in a second: 26 bytes each, all a block
    holds; 50 Hz). The gyro is integrated as its samples arrive, on the firmware's log
    timestamps (``control.gyro``): on the Kalman filter the pilots hold their attitude to it
    over seconds. Each
    odometry sample ticks the pilots it handed out (``PerchingPilot.tick_now``): their lateral
    loop closes at 50 Hz on odometry between camera frames.

    Each block is stamped on arrival (``time.monotonic``) so the pilots know how old the
    vehicle's senses are (``ages``): a stream that stops is stale, never "height stopped
    rising". A sample with a non-finite value is dropped whole (``rejected``; said once) and the
    last good one ages; so is one the sample gate refuses (``perchpose.io.samples``:
    implausible, out of order by the firmware's log timestamp, from before a reboot)."""

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
        self._odometry: tuple[Array, Array] | None = None
        self._f_body_mps2: Array | None = None
        self._pilots: list[PerchingPilot] = []
        self.clock: Callable[[], float] = time.monotonic  # stamps each block on arrival
        self._state_t_s = math.nan
        self._motion_t_s = math.nan
        self.rejected = 0
        self.gate = SampleGate()  # implausible, out of order (the firmware's ms), rebooted
        self._said: set[str] = set()
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
        for axis in ("x", "y", "z"):  # the body rates, integrated on arrival
            self._log.add_variable(f"gyro.{axis}", "FP16")
        self._gyro = GyroAttitude()
        self._log.data_received_cb.add_callback(self._state)
        self._motion = LogConfig(name="perchpose-odometry", period_in_ms=20)
        for axis in ("x", "y", "vx", "vy", "vz"):
            self._motion.add_variable(f"stateEstimate.{axis}", "float")
        for axis in ("x", "y", "z"):  # the body's specific force (x, y: the aerodynamic push)
            self._motion.add_variable(f"acc.{axis}", "FP16")
        self._motion.data_received_cb.add_callback(self._moved)
        try:
            for block in (self._log, self._motion):
                self.cf.log.add_config(block)
                block.start()
        except (KeyError, AttributeError) as exc:
            self._sync.close_link()
            raise LinkError(f"{uri}: the firmware does not log the state estimate: {exc}") from exc
        self.own_gains = self._read_velocity_gains()
        self.lean_lag_s = self._read_estimator()

    def _read_velocity_gains(self) -> dict[str, str]:
        """The firmware's horizontal velocity gains as they are (the pilots set theirs at
        take-over and give these back); empty, and said, where they cannot be read."""
        try:
            return {name: str(self.cf.param.get_value(name)) for name in VELOCITY_GAINS}
        except Exception as exc:  # cflib raises bare Exceptions; a missing name is a KeyError
            self.report(
                f"Crazyflie {self.uri}: cannot read {', '.join(VELOCITY_GAINS)} ({exc}): the "
                "pilots fly the vehicle's own velocity gains"
            )
            return {}

    def _read_estimator(self) -> float:
        """How long the vehicle's attitude estimate takes to miss a push's lean
        (``PilotSettings.lean_lag_s``): the Kalman filter's flying model has no drag (0 only
        where the vehicle says it runs the complementary filter, whose accelerometer finds the
        true vertical in a steady wind). A vehicle that does not say is taken to fly the
        Kalman filter, which a Flow deck's odometry needs."""
        try:
            chosen = int(self.cf.param.get_value(ESTIMATOR_PARAM))
        except Exception:  # cflib raises bare Exceptions; a missing name is a KeyError
            chosen = KALMAN_ESTIMATOR
        if chosen == COMPLEMENTARY_ESTIMATOR:
            return 0.0
        self.report(
            f"Crazyflie {self.uri}: the Kalman filter's attitude misses the lean a wind's push "
            f"needs; the pilots take it out over {CRAZYFLIE_KALMAN_LAG_S:g} s (control.lean)"
        )
        return CRAZYFLIE_KALMAN_LAG_S

    def _usable(self, data: dict[str, float]) -> bool:
        """All of a log block's values are finite; else it is dropped (said once)."""
        if all(math.isfinite(value) for value in data.values()):
            return True
        self.rejected += 1
        if self.rejected == 1:
            bad = sorted(name for name, value in data.items() if not math.isfinite(value))
            self.report(
                f"Crazyflie {self.uri}: a state estimate sample with non-finite "
                f"{', '.join(bad)} was dropped (reported once; the pilot flies on the last "
                "good one while it is fresh)"
            )
        return False

    def _refused(self, why: str | None, block: str) -> bool:
        """The sample gate refused a block (``why``): dropped, counted, each reason said once."""
        if why is None:
            return False
        self.rejected += 1
        if why not in self._said:
            self._said.add(why)
            self.report(
                f"Crazyflie {self.uri}: a {block} sample was dropped: {why} (reported once; "
                "the pilot flies on the last good one while it is fresh)"
            )
        return True

    def _state(self, timestamp: int, data: dict[str, float], _config: object) -> None:
        if not self._usable(data):
            return
        R = rotation_from_quaternion(
            data["stateEstimate.qw"],
            data["stateEstimate.qx"],
            data["stateEstimate.qy"],
            data["stateEstimate.qz"],
        )
        roll, pitch = roll_pitch_rad(R)
        now = self.clock()
        why = self.gate.attitude(int(timestamp), roll, pitch, yaw_rad(R), now)
        if self._refused(why, "attitude"):
            return
        self._R_world_body = R
        self._height_m = float(data["stateEstimate.z"])
        self._state_t_s = now
        rates_dps = [data["gyro.x"], data["gyro.y"], data["gyro.z"]]
        self._gyro.add(int(timestamp) / 1000.0, np.radians(np.array(rates_dps, np.float64)))

    def _moved(self, timestamp: int, data: dict[str, float], _config: object) -> None:
        if not self._usable(data):
            return
        now = self.clock()
        z = self._height_m if self._height_m is not None else 0.0
        p = np.array([data["stateEstimate.x"], data["stateEstimate.y"], z], np.float64)
        v = np.array(
            [data["stateEstimate.vx"], data["stateEstimate.vy"], data["stateEstimate.vz"]],
            np.float64,
        )
        if self._refused(self.gate.position(int(timestamp), p, v, now), "position"):
            return
        self._motion_t_s = now
        self._odometry = (p, v)
        self._f_body_mps2 = GRAVITY_MPS2 * np.array(
            [data["acc.x"], data["acc.y"], data["acc.z"]], np.float64
        )
        for pilot in self._pilots:  # the lateral loop closes at the state estimate's rate
            pilot.tick_now()

    def attitude(self) -> Array:
        return self._R_world_body

    def gyro(self) -> GyroReading | None:
        """The gyro integrated over the samples so far (None before the first)."""
        return self._gyro.reading()

    def odometry(self) -> tuple[Array, Array] | None:
        """Position and velocity (world frame, m, m/s) from the state estimate, or None."""
        return self._odometry

    def height_m(self) -> float | None:
        return self._height_m

    def specific_force(self) -> Array | None:
        """The accelerometer's body x, y and z (m/s^2; at rest +g along z) logged with the
        odometry, or None."""
        return self._f_body_mps2

    def ages(self) -> SenseAges:
        """How old the last attitude-and-height block and the last odometry block are."""
        now = self.clock()
        state_s = now - self._state_t_s if math.isfinite(self._state_t_s) else math.inf
        motion_s = now - self._motion_t_s if math.isfinite(self._motion_t_s) else math.inf
        # the odometry's z is the first block's height: it is only as fresh as both
        return SenseAges(state_s, max(state_s, motion_s), state_s)

    def pilot(self, settings: PilotSettings | None = None, **kwargs: Any) -> PerchingPilot:
        """A pilot on this link, told about a link loss; its settings take the vehicle's
        estimator's lean (``lean_lag_s``) unless they set their own."""
        settings = settings or PilotSettings()
        if settings.lean_lag_s == 0:
            settings = replace(settings, lean_lag_s=self.lean_lag_s)
        pilot = PerchingPilot(
            CflibCommander(self.cf.commander, self.cf.param, self.own_gains, self.cf.extpos),
            self.attitude,
            height_m=self.height_m,
            odometry=self.odometry,
            ages=self.ages,
            report=self.report,
            specific_force=self.specific_force,
            gyro=self.gyro,
            settings=settings,
            **kwargs,
        )
        pilot.watch_link(self.cf)
        self._pilots.append(pilot)
        return pilot

    def close(self) -> None:
        try:
            self._log.stop()
            self._motion.stop()
        finally:
            self._sync.close_link()


def connect(uri: str, report: Callable[[str], None] | None = None) -> CrazyflieConnection:
    """Open ``uri`` (e.g. ``radio://0/80/2M/E7E7E7E7E7``) and stream the vehicle's state."""
    if not uri.startswith(("radio://", "usb://", "udp://", "tcp://", "debug://")):
        raise LinkError(f"Crazyflie URI {uri!r}: expected e.g. radio://0/80/2M/E7E7E7E7E7")
    return CrazyflieConnection(uri, report)
