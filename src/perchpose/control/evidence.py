"""What the vehicle's own height says about its end: contact with the plate during the final
climb, and touchdown during a landing. Both read a window of live height samples; a gap (no live
height) starts the window again, so neither is ever read across one."""

from __future__ import annotations

import math
from collections import deque


class HeightWindow:
    """The live height samples ``(t_s, height_m)`` of the last ``window_s`` seconds (with the
    newest one at or before its start, so a full window spans ``window_s``)."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self.samples: deque[tuple[float, float]] = deque()

    def reset(self) -> None:
        self.samples.clear()

    def add(self, t_s: float, height_m: float | None) -> bool:
        """Add a sample; True once the samples span a whole window. None or non-finite (no
        live height) empties the window."""
        if height_m is None or not math.isfinite(height_m):
            self.reset()
            return False
        self.samples.append((t_s, height_m))
        while len(self.samples) > 1 and t_s - self.samples[1][0] >= self.window_s:
            self.samples.popleft()
        return t_s - self.samples[0][0] >= self.window_s

    def heights(self) -> list[float]:
        return [h for _, h in self.samples]


class ContactDetector:
    """Contact evidence: during the final climb, the height stopped rising (it rose less than
    ``rise_m`` over a whole ``window_s``); with ``either_way``, while backing off from the
    plate, the height stopped moving at all (it stayed within ``rise_m``: the magnet holds
    the vehicle against the plate)."""

    def __init__(self, window_s: float, rise_m: float, either_way: bool = False) -> None:
        self.rise_m = rise_m
        self.either_way = either_way
        self._window = HeightWindow(window_s)

    def reset(self) -> None:
        self._window.reset()

    def touched(self, t_s: float, height_m: float | None) -> bool:
        """Add a height sample of the final climb; True once the height has risen less than
        ``rise_m`` over a whole window."""
        if not self._window.add(t_s, height_m):
            return False
        heights = self._window.heights()
        low = min(heights) if self.either_way else heights[0]
        return max(heights) - low < self.rise_m


class TouchdownDetector:
    """Touchdown evidence while landing: over a whole ``window_s`` every live height was under
    ``landed_height_m`` and the height moved less than ``still_m``, and the vertical speed
    (where the vehicle gives one) is under ``speed_mps``. A vehicle that hovers above the
    ground (it does not descend) is never read as landed, however still it holds."""

    def __init__(
        self, window_s: float, still_m: float, landed_height_m: float, speed_mps: float
    ) -> None:
        self.still_m = still_m
        self.landed_height_m = landed_height_m
        self.speed_mps = speed_mps
        self._window = HeightWindow(window_s)

    def reset(self) -> None:
        self._window.reset()

    def touched(self, t_s: float, height_m: float | None, vz_mps: float | None) -> bool:
        """Add a height sample of the landing (``vz_mps``: the vertical speed, None if
        unknown); True once the vehicle rests on the ground."""
        if not self._window.add(t_s, height_m):
            return False
        heights = self._window.heights()
        low = max(heights) < self.landed_height_m
        still = max(heights) - min(heights) < self.still_m
        slow = vz_mps is None or (math.isfinite(vz_mps) and abs(vz_mps) < self.speed_mps)
        return low and still and slow
