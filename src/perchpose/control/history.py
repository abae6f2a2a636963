"""Time-stamped samples looked up by time: the attitudes a late fix is placed with, the
disturbance observer's past estimates a late velocity is compared with, and the simulated
flight controller's samples handed out late."""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Sequence
from operator import itemgetter
from typing import Any, TypeVar

T = TypeVar("T")
TIME_TOLERANCE_S = 1e-9  # a sample this close after ``t_s`` still counts as at it


def index_at(samples: Sequence[tuple[Any, ...]], t_s: float) -> int:
    """The index of the newest sample made at or before ``t_s`` (-1 when all came after it).
    ``samples``: tuples whose first item is the time, in time order."""
    return bisect_right(samples, t_s + TIME_TOLERANCE_S, key=itemgetter(0)) - 1


def newest_at(samples: Sequence[tuple[float, T]], t_s: float) -> T:
    """The value of the newest sample made at or before ``t_s`` (the oldest one's when all
    came after it). ``samples``: (time, value), in time order, not empty."""
    return samples[max(0, index_at(samples, t_s))][1]
