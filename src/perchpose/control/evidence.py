"""What the vehicle's own height says about its end: contact with the plate during the final
climb, and touchdown during a landing. Both read a window of live height samples; a gap (no live
height) starts the window again, so neither is ever read across one."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Sequence
from itertools import chain, islice


def line_at(samples: Sequence[tuple[float, float]], t_s: float) -> float:
    """The least-squares line through ``samples`` ((t_s, height_m), at least one), at
    ``t_s`` (their mean where they span no time)."""
    n = len(samples)
    t_mean = sum(t for t, _ in samples) / n
    h_mean = sum(h for _, h in samples) / n
    spread = sum((t - t_mean) ** 2 for t, _ in samples)
    if spread <= 0.0:
        return h_mean
    slope = sum((t - t_mean) * (h - h_mean) for t, h in samples) / spread
    return h_mean + slope * (t_s - t_mean)


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
    ``rise_m`` over a whole ``window_s``)."""

    def __init__(self, window_s: float, rise_m: float) -> None:
        self.rise_m = rise_m
        self._window = HeightWindow(window_s)

    def reset(self) -> None:
        self._window.reset()

    def touched(self, t_s: float, height_m: float | None) -> bool:
        """Add a height sample of the final climb; True once the height has risen less than
        ``rise_m`` over a whole window."""
        if not self._window.add(t_s, height_m):
            return False
        heights = self._window.heights()
        return max(heights) - heights[0] < self.rise_m


class HeldDetector:
    """Contact evidence near the plate in any phase: over each half of a whole ``window_s``
    the vertical speeds asked for would have moved the vehicle at least ``still_m`` (the same
    way in both), and its height's trend (the least-squares line through the window's
    samples) moved less than ``still_m``: something holds it (the magnet, against the
    plate). Where the caller knows the vehicle was at the plate a moment before, a trend
    against the asking counts as held too (``against``): a Kalman filter's height drifts
    while the plate holds the vehicle (it takes the thrust's lean against the plate for
    acceleration), while a vehicle following what it is asked moves with it; elsewhere a
    gust can lift a free vehicle against the asking. A vehicle in free air follows what it
    is asked with a lag of a few tenths of a second, so its trend moves at least
    ``2 still_m`` less that lag's worth. The trend, not
    the samples' spread, so that a height estimate with a centimetre of noise (a Kalman
    filter's on a range sensor 2 m from the floor) still reads a vehicle held still. Both
    halves, so that a window whose asking began halfway (a hover, then a descent) is not
    read as held while the vehicle is only starting to follow it: a vehicle the plate held
    in the hover, leaving it as the descent is asked, has a flat trend across the two."""

    def __init__(self, window_s: float, still_m: float) -> None:
        self.still_m = still_m
        self._window = HeightWindow(window_s)
        self._asked: deque[tuple[float, float]] = deque()  # (t_s, asked vertical speed)

    def reset(self) -> None:
        self._window.reset()
        self._asked.clear()

    def touched(
        self, t_s: float, height_m: float | None, asked_z_mps: float, *, against: bool = False
    ) -> bool:
        """Add a height sample and the vertical speed asked for then; True once the
        vehicle has held still against a whole window of asking (``against``: or its height
        moved against the asking, where something else says it is at the plate)."""
        if not self._window.add(t_s, height_m):
            if not self._window.samples:
                self._asked.clear()
            else:
                self._asked.append((t_s, asked_z_mps))
            return False
        self._asked.append((t_s, asked_z_mps))
        start = self._window.samples[0][0]
        while len(self._asked) > 1 and self._asked[1][0] <= start:
            self._asked.popleft()
        middle = start + 0.5 * (t_s - start)
        first, second = self._asked_m(start, middle), self._asked_m(middle, t_s)
        asked = first * second > 0.0 and min(abs(first), abs(second)) >= self.still_m
        trend = self._trend_m()
        moved = trend * math.copysign(1.0, first) if against else abs(trend)
        return asked and moved < self.still_m

    def _asked_m(self, start_s: float, end_s: float) -> float:
        """How far the vertical speeds asked for would have moved the vehicle from
        ``start_s`` to ``end_s`` (each held until the next)."""
        ends = chain(islice(self._asked, 1, None), [(math.inf, 0.0)])
        return sum(
            v * max(0.0, min(t1, end_s) - max(t0, start_s))
            for (t0, v), (t1, _) in zip(self._asked, ends, strict=True)
        )

    def _trend_m(self) -> float:
        """How far the least-squares line through the window's heights moves across it."""
        samples = self._window.samples
        return line_at(samples, samples[-1][0]) - line_at(samples, samples[0][0])


class RigidDetector:
    """Rigidity evidence from the accelerometer: over the last ``window_s`` its vertical
    specific force (body z) spread less than ``spread_mps2`` (standard deviation). A vehicle
    the plate holds does not move: the plate takes every change of thrust, and its
    accelerometer reads gravity and its own noise. A vehicle in free air takes them as
    vertical acceleration; its loops change the thrust all the time in gusts, exactly where a
    filter's drifting velocity can hold it at a height against what it is asked. Samples come
    as the link delivers them; one read again unchanged is not a new sample."""

    MIN_SAMPLES = 4  # fewer in a window says nothing either way

    def __init__(self, window_s: float, spread_mps2: float) -> None:
        self.window_s = window_s
        self.spread_mps2 = spread_mps2
        self._samples: deque[tuple[float, float]] = deque()  # (t_s, body z, m/s^2)
        self._last: tuple[float, ...] | None = None

    def add(self, t_s: float, f_body_mps2: Iterable[float] | None) -> None:
        """Add the accelerometer's latest sample (body x, y, z; None or non-finite: none)."""
        if f_body_mps2 is None:
            return
        sample = tuple(float(f) for f in f_body_mps2)
        if len(sample) < 3:
            return
        if not all(math.isfinite(f) for f in sample) or sample == self._last:
            return
        self._last = sample
        self._samples.append((t_s, sample[2]))
        self._forget_before(t_s)

    def rigid(self, t_s: float) -> bool | None:
        """True where the window's samples spread less than ``spread_mps2``, False where
        more; None where the window holds too few to say (no accelerometer on the link)."""
        self._forget_before(t_s)
        n = len(self._samples)
        if n < self.MIN_SAMPLES:
            return None
        mean = sum(f for _, f in self._samples) / n
        spread = math.sqrt(sum((f - mean) ** 2 for _, f in self._samples) / (n - 1))
        return spread < self.spread_mps2

    def _forget_before(self, t_s: float) -> None:
        """Drop the samples older than a window before ``t_s``."""
        while self._samples and t_s - self._samples[0][0] > self.window_s:
            self._samples.popleft()


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
