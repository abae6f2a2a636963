"""Which of a vehicle's attitude and position samples may be flown on (MAVLink's ATTITUDE and
LOCAL_POSITION_NED, the Crazyflie's state estimate log blocks).

A sample is refused, with its reason counted, when it is

- ``non-finite``: a NaN or infinite field;
- ``implausible``: an angle outside its range, a tilt beyond what the vehicle flies
  (``max_tilt_deg``), a position further
  from the local origin than ``max_position_m``, a speed over ``max_speed_mps``, or a position
  that moved further since the last sample taken than that speed allows (plus ``jump_m``);
- ``out of order``: its ``time_boot_ms`` is not after the last one taken of its kind (a replay,
  a duplicate, a link that reorders);
- ``before reboot``: after the autopilot rebooted, a sample stamped on its old clock.

The autopilot's clock going back is a reboot only when nothing on the old clock arrives for
``reboot_confirm_s`` while the new one runs (a replay of old samples interleaves with the live
stream and never is); the samples of the new clock are then taken, ``reboots`` counts it and
``on_reboot`` is called (the link restarts its TIMESYNC). A position that keeps jumping the same
way for ``reboot_confirm_s`` is an estimator reset and is taken from then on.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
REASONS = ("non-finite", "implausible", "out of order", "before reboot")


@dataclass(frozen=True)
class SampleLimits:
    """What a multirotor perching or landing can do (SI units, degrees for the tilt)."""

    max_tilt_deg: float = 60.0
    max_position_m: float = 10_000.0
    max_speed_mps: float = 30.0
    jump_m: float = 0.5
    reboot_confirm_s: float = 0.5


class _Timeline:
    """One kind of sample's ``time_boot_ms``: the last taken, and a new clock that may be a
    reboot (its first local time)."""

    def __init__(self) -> None:
        self.last_ms: int | None = None
        self.old_ms: int | None = None  # the last time on the clock before a reboot
        self.back_since_s: float | None = None


class SampleGate:
    """Checks each sample of one vehicle (``attitude``, ``position``): None to take it, or the
    reason it is refused (also counted in ``refused``)."""

    def __init__(
        self,
        limits: SampleLimits | None = None,
        on_reboot: Callable[[str], None] | None = None,
    ) -> None:
        self.limits = limits or SampleLimits()
        self.on_reboot = on_reboot
        self.refused: Counter[str] = Counter()
        self.reboots = 0
        self._timelines = {"ATTITUDE": _Timeline(), "LOCAL_POSITION_NED": _Timeline()}
        self._p_m: Array | None = None
        self._p_ms: int | None = None
        self._jump_since_s: float | None = None

    def _refuse(self, reason: str) -> str:
        self.refused[reason] += 1
        return reason

    def _in_order(self, kind: str, time_boot_ms: int, now_s: float) -> str | None:
        line = self._timelines[kind]
        if line.old_ms is not None and time_boot_ms >= line.old_ms:
            step_ms = math.inf if line.last_ms is None else time_boot_ms - line.last_ms
            if step_ms > 1000.0 * self.limits.reboot_confirm_s:
                return "before reboot"  # the old clock, late: the new one is well behind it
            line.old_ms = None  # the new clock has caught up with the old one
        if line.last_ms is None or time_boot_ms >= line.last_ms:  # a repeat is harmless
            line.back_since_s = None
            line.last_ms = time_boot_ms
            return None
        if line.back_since_s is None:
            line.back_since_s = now_s
        if now_s - line.back_since_s < self.limits.reboot_confirm_s:
            return "out of order"
        # only the new clock for a while: the autopilot rebooted, for every kind of sample
        for other in self._timelines.values():
            if other.last_ms is not None:
                other.old_ms, other.last_ms, other.back_since_s = other.last_ms, None, None
        line.last_ms = time_boot_ms
        self._p_m = None
        self.reboots += 1
        if self.on_reboot is not None:
            self.on_reboot(f"the autopilot's clock went back to {time_boot_ms / 1000:.1f} s")
        return None

    def attitude(
        self, time_boot_ms: int, roll_rad: float, pitch_rad: float, yaw_rad: float, now_s: float
    ) -> str | None:
        """None to take this ATTITUDE, else why not."""
        if not all(math.isfinite(v) for v in (roll_rad, pitch_rad, yaw_rad)):
            return self._refuse("non-finite")
        in_range = abs(roll_rad) <= math.pi + 1e-6 and abs(pitch_rad) <= math.pi / 2 + 1e-6
        if not (in_range and abs(yaw_rad) <= 2 * math.pi):
            return self._refuse("implausible")  # not an angle ATTITUDE can carry
        limit = math.radians(self.limits.max_tilt_deg)
        tilt = math.acos(max(-1.0, min(1.0, math.cos(roll_rad) * math.cos(pitch_rad))))
        if tilt > limit:
            return self._refuse("implausible")
        order = self._in_order("ATTITUDE", time_boot_ms, now_s)
        return None if order is None else self._refuse(order)

    def position(self, time_boot_ms: int, p_m: Array, v_mps: Array, now_s: float) -> str | None:
        """None to take this LOCAL_POSITION_NED (``p_m``, ``v_mps``: (3,) NED), else why not."""
        lim = self.limits
        if not (np.all(np.isfinite(p_m)) and np.all(np.isfinite(v_mps))):
            return self._refuse("non-finite")
        if np.linalg.norm(p_m) > lim.max_position_m or np.linalg.norm(v_mps) > lim.max_speed_mps:
            return self._refuse("implausible")
        order = self._in_order("LOCAL_POSITION_NED", time_boot_ms, now_s)
        if order is not None:
            return self._refuse(order)
        if self._p_m is not None and self._p_ms is not None:
            dt_s = max(0.0, (time_boot_ms - self._p_ms) / 1000.0)
            if np.linalg.norm(p_m - self._p_m) > lim.max_speed_mps * dt_s + lim.jump_m:
                if self._jump_since_s is None:
                    self._jump_since_s = now_s
                if now_s - self._jump_since_s < lim.reboot_confirm_s:
                    return self._refuse("implausible")
        self._jump_since_s = None
        self._p_m, self._p_ms = np.array(p_m, np.float64), time_boot_ms
        return None
