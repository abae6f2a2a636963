"""Faults injected into a perching run, one drawn per run, as the deployed pilot meets them.

- ``camera-stall``: no frame reaches the pilot (a stream that waits on its timeout and its
  reconnection, a USB camera that hangs) for 0.5-8 s; the source stays open;
- ``odometry-stall``, ``attitude-stall``: the flight controller's position or attitude stops
  reaching the pilot (a log block or a MAVLink stream that stops) for 0.2-3 s;
- ``link-loss``: no setpoint reaches the vehicle for 0.2-3 s. The Crazyflie's commander
  watchdog (firmware ``COMMANDER_WDT_TIMEOUT_STABILIZE``, ``_SHUTDOWN``) levels the vehicle
  after 0.5 s without a setpoint (here: a hover) and stops its motors after 2 s.

Each starts at a time drawn uniformly in 1-8 s, during the approach.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from perchpose.errors import VehicleConfigError

FAULTS = ("camera-stall", "odometry-stall", "attitude-stall", "link-loss")
DURATIONS_S = {
    "camera-stall": (0.5, 8.0),
    "odometry-stall": (0.2, 3.0),
    "attitude-stall": (0.2, 3.0),
    "link-loss": (0.2, 3.0),
}
START_S = (1.0, 8.0)
LEVEL_AFTER_S = 0.5  # the Crazyflie's watchdog: no setpoint this long, level (hover)
MOTORS_OFF_AFTER_S = 2.0  # and this long, motors off


def check_faults(names: tuple[str, ...]) -> tuple[str, ...]:
    """``names`` if each is a fault this module injects, else ``VehicleConfigError``."""
    unknown = [n for n in names if n not in FAULTS]
    if unknown:
        raise VehicleConfigError(f"unknown fault {unknown[0]!r} (choose from {', '.join(FAULTS)})")
    if len(set(names)) != len(names):
        raise VehicleConfigError(f"--faults names a fault twice: {','.join(names)}")
    return names


@dataclass(frozen=True)
class Fault:
    """One run's fault: what, from when, for how long (s)."""

    kind: str
    start_s: float
    duration_s: float

    def active(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.start_s + self.duration_s

    @staticmethod
    def draw(kinds: tuple[str, ...], rng: np.random.Generator) -> Fault | None:
        """One of ``kinds`` (None when there are none) with its start and duration."""
        if not kinds:
            return None
        kind = kinds[int(rng.integers(len(kinds)))]
        return Fault(kind, float(rng.uniform(*START_S)), float(rng.uniform(*DURATIONS_S[kind])))
