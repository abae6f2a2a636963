"""A detection's time budget: the deadline of the current frame, what the frame left out to keep
it, the time its corner fits took, and the costs learnt across frames from which each step's
cost is predicted (a pattern fit per square pixel of marker side, a whole-frame search, a
quick look)."""

from __future__ import annotations

import time

# A pattern fit's first predicted cost, seconds per square pixel of the marker's side (10 ms
# at 45 px: what a fit on 2x2 blocks under the harsh preset's blur cost on a 2-core x86
# machine before the model merged its bands; about 1.5 ms now); each fit run updates the
# prediction.
PATTERN_S_PER_PX2 = 5e-6
# Each learnt cost (a pattern fit's per square pixel, a whole-frame search's, a quick look's)
# moves this fraction of the way to each new run's.
COST_UPDATE = 0.3


def learnt(cost_s: float, measured_s: float) -> float:
    """A learnt cost moved ``COST_UPDATE`` of the way to the one just measured."""
    return cost_s + COST_UPDATE * (measured_s - cost_s)


class Budget:
    """One ``MarkerDetector``'s budget: ``start`` each frame with its deadline (a
    ``time.perf_counter()`` reading, or None), then ``late(more_s)`` says whether that much more
    work would end past it and ``skip(label)`` records what was left out for it."""

    def __init__(self) -> None:
        self.deadline_s: float | None = None
        self.skipped: list[str] = []
        self.corners_s = 0.0  # seconds spent fitting corners in this frame
        self.pattern_s_per_px2 = PATTERN_S_PER_PX2
        self.search_s = 0.0  # a thorough whole-frame search's cost, learnt
        self.quick_s = 0.0  # a quick look's, learnt

    def start(self, deadline_s: float | None) -> None:
        self.deadline_s = deadline_s
        self.skipped = []
        self.corners_s = 0.0

    def late(self, more_s: float) -> bool:
        """Whether ``more_s`` seconds of work from now would end past the deadline."""
        deadline = self.deadline_s
        return deadline is not None and time.perf_counter() + more_s > deadline

    def skip(self, label: str) -> None:
        self.skipped.append(label)

    def pattern_fitted(self, spent_s: float, side_px: float) -> None:
        """A pattern fit of a marker of ``side_px`` took ``spent_s``."""
        self.pattern_s_per_px2 = learnt(self.pattern_s_per_px2, spent_s / max(1.0, side_px**2))
