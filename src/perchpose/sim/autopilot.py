"""A stand-in autopilot's flight modes: what ArduCopter and PX4 do with a vehicle that a
companion computer flies by velocity setpoints.

Three kinds of mode, each with the autopilots' own names and numbers:

- **hold** (ArduCopter LOITER 5; PX4 POSCTL, main mode 3, and AUTO.LOITER): the vehicle holds
  the position where the mode began (a proportional loop of ``hold_gain_per_s`` on the
  vehicle's velocity loop, at most ``max_hold_mps``);
- **setpoints** (ArduCopter GUIDED 4; PX4 OFFBOARD, main mode 6): the vehicle flies the last
  velocity and yaw-rate setpoint. ArduCopter stops (holds where it is) when no setpoint came
  for ``guided_timeout_s`` (3 s, as its GUIDED velocity control does); PX4 enters OFFBOARD
  only while setpoints stream at over ``offboard_min_rate_hz`` (2 Hz) and leaves it for
  POSCTL when none came for ``offboard_loss_s`` (``COM_OF_LOSS_T``, 1 s by default);
- **land** (ArduCopter LAND 9; PX4 AUTO.LAND): down at ``land_speed_mps`` holding its
  horizontal position, disarmed on touchdown.

A normal disarm is taken only on the ground; a forced one (MAV_CMD_COMPONENT_ARM_DISARM with
21196) always, as both autopilots do. Positions and velocities are in the simulation's world
frame (z up); ``perchpose.io.mavlink.vehicle_endpoint`` turns them to and from NED.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from perchpose.errors import VehicleConfigError

Array = NDArray[np.float64]

AUTOPILOTS = ("ardupilot", "px4")
MAV_AUTOPILOT = {"ardupilot": 3, "px4": 12}  # MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_PX4


def _px4(main: int, sub: int = 0) -> int:
    """PX4's custom_mode: its main mode in the third byte, its sub mode in the fourth."""
    return (main << 16) | (sub << 24)


# (custom_mode, kind) of each mode by its name
MODES: dict[str, dict[str, tuple[int, str]]] = {
    "ardupilot": {"LOITER": (5, "hold"), "GUIDED": (4, "setpoints"), "LAND": (9, "land")},
    "px4": {
        "POSCTL": (_px4(3), "hold"),
        "AUTO.LOITER": (_px4(4, 3), "hold"),
        "OFFBOARD": (_px4(6), "setpoints"),
        "AUTO.LAND": (_px4(4, 6), "land"),
    },
}
HOLD_MODE = {"ardupilot": "LOITER", "px4": "POSCTL"}
SETPOINT_MODE = {"ardupilot": "GUIDED", "px4": "OFFBOARD"}


@dataclass(frozen=True)
class AutopilotSettings:
    """The stand-in's constants (see the module's description)."""

    hold_gain_per_s: float = 1.0
    max_hold_mps: float = 1.0
    land_speed_mps: float = 0.5  # ArduCopter's LAND_SPEED, 50 cm/s
    guided_timeout_s: float = 3.0
    offboard_loss_s: float = 1.0
    offboard_min_rate_hz: float = 2.0


class StandInAutopilot:
    """The modes, arming and setpoints of one vehicle. ``kind``: ``ardupilot`` or ``px4``;
    it starts armed in its hold mode, holding ``p_m``. ``events`` collects one line per
    thing that happened (a mode change and why, a disarm, a refusal)."""

    def __init__(self, kind: str, p_m: Array, settings: AutopilotSettings | None = None) -> None:
        if kind not in AUTOPILOTS:
            raise VehicleConfigError(f"unknown autopilot {kind!r} (choose {', '.join(AUTOPILOTS)})")
        self.kind = kind
        self.settings = settings or AutopilotSettings()
        self.mode = HOLD_MODE[kind]
        self.armed = True
        self.hold_p_m = np.asarray(p_m, np.float64).copy()
        self.v_sp_mps = np.zeros(3)
        self.p_sp_m: Array | None = None  # a position setpoint (None: velocity)
        self.yaw_rate_rad_s = 0.0
        self._setpoint_s: float | None = None
        self._stream: deque[float] = deque(maxlen=64)  # when setpoints arrived
        self.setpoints = 0  # taken in the setpoint mode
        self.events: list[str] = []

    @property
    def modes(self) -> dict[str, int]:
        """This autopilot's modes: custom_mode by name."""
        return {name: number for name, (number, _) in MODES[self.kind].items()}

    @property
    def custom_mode(self) -> int:
        return MODES[self.kind][self.mode][0]

    @property
    def kind_of_mode(self) -> str:
        return MODES[self.kind][self.mode][1]

    @property
    def takes_setpoints(self) -> bool:
        return self.kind_of_mode == "setpoints"

    def mode_named(self, custom_mode: int) -> str | None:
        """The name of a custom mode of this autopilot (None: one it does not have)."""
        for name, (number, _) in MODES[self.kind].items():
            if number == custom_mode:
                return name
        return None

    def _enter(self, name: str, p_m: Array, why: str) -> None:
        if name == self.mode:
            return
        self.mode = name
        self.hold_p_m = np.asarray(p_m, np.float64).copy()
        self.v_sp_mps = np.zeros(3)
        self.p_sp_m = None
        self.yaw_rate_rad_s = 0.0
        self._setpoint_s = None
        self.events.append(f"mode {name} ({why})")

    def streaming(self, t_s: float) -> bool:
        """Setpoints have come at over ``offboard_min_rate_hz`` for the last second."""
        recent = [s for s in self._stream if t_s - 1.0 <= s <= t_s]
        return len(recent) > self.settings.offboard_min_rate_hz

    def set_mode(self, custom_mode: int, t_s: float, p_m: Array, why: str) -> str:
        """A mode change asked for: '' when taken, else why it was refused."""
        name = self.mode_named(custom_mode)
        if name is None:
            return f"custom mode {custom_mode} is not one this stand-in flies"
        if not self.armed and MODES[self.kind][name][1] != "land":
            return "disarmed"
        if self.kind == "px4" and name == "OFFBOARD" and not self.streaming(t_s):
            return "no setpoint stream (PX4 needs one at over 2 Hz before OFFBOARD)"
        self._enter(name, p_m, why)
        return ""

    def setpoint(self, v_world_mps: Array, yaw_rate_rad_s: float, t_s: float) -> bool:
        """A velocity setpoint arrived: flown in the setpoint mode (True), otherwise only
        counted towards PX4's stream (False)."""
        if not self._take(v_world_mps, yaw_rate_rad_s, t_s):
            return False
        self.v_sp_mps, self.p_sp_m = np.asarray(v_world_mps, np.float64).copy(), None
        return True

    def position_setpoint(self, p_world_m: Array, yaw_rate_rad_s: float, t_s: float) -> bool:
        """A position setpoint arrived: flown to (with the hold mode's loop) in the setpoint
        mode (True), otherwise only counted towards PX4's stream (False)."""
        if not self._take(p_world_m, yaw_rate_rad_s, t_s):
            return False
        self.p_sp_m = np.asarray(p_world_m, np.float64).copy()
        return True

    def _take(self, vector: Array, yaw_rate_rad_s: float, t_s: float) -> bool:
        self._stream.append(t_s)
        if not (self.armed and self.takes_setpoints):
            return False
        if not (np.isfinite(vector).all() and math.isfinite(yaw_rate_rad_s)):
            self.events.append("a non-finite setpoint refused")
            return False
        self.yaw_rate_rad_s = float(yaw_rate_rad_s)
        self._setpoint_s = t_s
        self.setpoints += 1
        return True

    def arm(self, on_ground: bool, p_m: Array) -> str:
        """An arm asked for: '' when taken (it holds where it stands, in its hold mode),
        else why it was refused."""
        if self.armed:
            return ""
        if not on_ground:
            return "not on the ground"
        self.armed = True
        self._enter(HOLD_MODE[self.kind], p_m, "armed")
        self.hold_p_m = np.asarray(p_m, np.float64).copy()
        self.events.append("armed")
        return ""

    def disarm(self, force: bool, on_ground: bool) -> str:
        """A disarm asked for: '' when taken, else why it was refused."""
        if not self.armed:
            return ""
        if not (force or on_ground):
            return "in the air (a forced disarm is needed)"
        self.armed = False
        self.events.append("disarmed" + (" (forced)" if force else ""))
        return ""

    def command(self, t_s: float, p_m: Array, on_ground: bool) -> tuple[Array, float]:
        """The velocity (world frame, m/s) and yaw rate (rad/s) the vehicle's own loops fly
        now, from its position ``p_m``; ends a landing on the ground and a setpoint mode
        whose setpoints stopped."""
        s = self.settings
        if self.armed and self.takes_setpoints and self._setpoint_s is not None:
            silent_s = t_s - self._setpoint_s
            if self.kind == "px4" and silent_s > s.offboard_loss_s:
                self._enter("POSCTL", p_m, f"no setpoint for {s.offboard_loss_s:g} s")
            elif self.kind == "ardupilot" and silent_s > s.guided_timeout_s:
                self.hold_p_m = np.asarray(p_m, np.float64).copy()
                self._setpoint_s = None
                self.events.append(f"GUIDED: no setpoint for {s.guided_timeout_s:g} s, holding")
        if self.takes_setpoints and self._setpoint_s is not None and self.p_sp_m is None:
            return self.v_sp_mps, self.yaw_rate_rad_s
        target, yaw_rate = self.hold_p_m, 0.0
        if self.takes_setpoints and self._setpoint_s is not None and self.p_sp_m is not None:
            target, yaw_rate = self.p_sp_m, self.yaw_rate_rad_s
        error = target - np.asarray(p_m, np.float64)
        v = s.hold_gain_per_s * error
        if self.kind_of_mode == "land":
            if on_ground and self.armed:
                self.disarm(False, True)
            v[2] = -s.land_speed_mps
        speed = float(np.linalg.norm(v[:2]))
        if speed > s.max_hold_mps:
            v[:2] *= s.max_hold_mps / speed
        v[2] = max(-s.max_hold_mps, min(s.max_hold_mps, float(v[2])))
        return v, yaw_rate
