"""Time-stamped samples looked up by time: the attitudes a late fix is placed with, the
disturbance observer's past estimates a late velocity is compared with, and the simulated
flight controller's samples handed out late."""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Sequence
from operator import itemgetter
from typing import TypeVar

T = TypeVar("T")
TIME_TOLERANCE_S = 1e-9  # a sample this close after ``t_s`` still counts as at it


def newest_at(samples: Sequence[tuple[float, T]], t_s: float) -> T:
    """The value of the newest sample made at or before ``t_s`` (the oldest one's when all
    came after it). ``samples``: (time, value), in time order, not empty."""
    i = bisect_right(samples, t_s + TIME_TOLERANCE_S, key=itemgetter(0))
    return samples[max(0, i - 1)][1]
