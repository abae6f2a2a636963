"""The magnet's hold, tried before the motors stop.

Contact evidence (``perchpose.control.pilot``) says the vehicle is against the plate; it does
not say that the magnet holds it. A gear pressed against the plate beyond the magnet's hold
(about 23 mm off its centre) reads as still as a seated one while the motors push it there,
and falls once they stop. So for ``PilotSettings.seat_check_s`` before the stop the pilot
sends a level thrust under the hover's (``seat_check_thrust``), or, on a link without one, a
descent (``seat_check_mps``): a vehicle the magnet holds stays at the plate, and one it does
not hold comes away from it.

``SeatCheck`` judges on what the pilot hands it: ``DROPPED`` once the accelerometer's vertical
specific force (body z) read under ``fall_mps2`` twice running (a vehicle the plate holds
reads about g whatever its thrust; one let go on a quarter of its hover thrust reads about a
quarter of g), or once a live height is more than ``drop_m`` under the height the check began
at; ``HELD`` once live heights have spanned the whole window without either. The height is
the slower word: a Flow deck's filter 2 m from the floor wanders a few centimetres while the
plate holds the vehicle still (3 cm down in 0.4 s in a traced run of a vehicle seated 11 mm
off-centre), so ``drop_m`` is set above that, and the accelerometer, where the link gives
it, decides first. A check without a live height goes on until one comes; the pilot keeps
asking meanwhile (a vehicle the magnet holds does not move, one it does not hold comes down).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum

__all__ = ["SeatCheck", "SeatChecks", "SeatVerdict"]

FALLING_READINGS = 2  # accelerometer readings under the limit running that say the vehicle fell


class SeatVerdict(StrEnum):
    """What a finished check found."""

    HELD = "held"
    DROPPED = "dropped"


@dataclass
class SeatCheck:
    """One check, begun at ``started_s`` with the vehicle at ``height_m`` (None: no live
    height then; the first live one is taken), after the contact evidence ``why``."""

    started_s: float
    height_m: float | None
    why: str
    lowest_m: float = field(default=math.inf, init=False)
    falling: int = field(default=0, init=False)  # accelerometer readings under fall_mps2 running

    def verdict(
        self,
        t_s: float,
        height_m: float | None,
        f_z_mps2: float | None,
        limits: tuple[float, float, float],
    ) -> SeatVerdict | None:
        """The verdict at ``t_s`` with the live height ``height_m`` (None: not live) and the
        accelerometer's vertical specific force ``f_z_mps2`` (None: not given), against
        ``limits`` = (window_s, drop_m, fall_mps2); None while the window is not spanned."""
        window_s, drop_m, fall_mps2 = limits
        if f_z_mps2 is not None and math.isfinite(f_z_mps2):
            self.falling = self.falling + 1 if f_z_mps2 < fall_mps2 else 0
            if self.falling >= FALLING_READINGS:
                return SeatVerdict.DROPPED
        if height_m is None or not math.isfinite(height_m):
            return None
        if self.height_m is None:
            self.height_m = height_m
        self.lowest_m = min(self.lowest_m, height_m)
        if self.height_m - self.lowest_m > drop_m:
            return SeatVerdict.DROPPED
        if t_s - self.started_s >= window_s:
            return SeatVerdict.HELD
        return None

    @property
    def drop_m(self) -> float:
        """How far the vehicle came down since the check began (0 before a live height)."""
        if self.height_m is None or not math.isfinite(self.lowest_m):
            return 0.0
        return max(0.0, self.height_m - self.lowest_m)


@dataclass
class SeatChecks:
    """A pilot's checks: the one under way (None: none) and how many the vehicle came down
    in (the magnet did not hold it)."""

    now: SeatCheck | None = None
    drops: int = 0
