import math
from collections.abc import Callable

import numpy as np
import pytest

from perchpose.evaluation.latency import (
    CYCLE,
    DIGITS,
    LatencyMeter,
    MarkerReader,
    count_of,
    display_image,
)


@pytest.mark.parametrize("count", [0, 1, 24, 25, 26, 311, CYCLE - 1])
def test_each_count_is_read_back_through_a_camera(
    count: int, film_screen: Callable[[np.ndarray, np.random.Generator], np.ndarray]
) -> None:
    rng = np.random.default_rng(count)
    ids = MarkerReader().ids(film_screen(display_image(count), rng))
    assert count_of(ids) == count


def test_a_frame_without_one_marker_of_each_kind_gives_no_count() -> None:
    assert count_of([]) is None
    assert count_of([3]) is None
    assert count_of([3, DIGITS + 1, 4]) is None  # caught between two counts: ambiguous
    assert count_of([3, DIGITS + 1]) == DIGITS + 3


def test_the_meter_dates_a_frame_from_the_middle_of_its_count_s_display() -> None:
    meter = LatencyMeter(display_period_s=0.02, display_lag_s=0.005)
    for c in range(100):
        meter.shown(c, 10.0 + 0.02 * c)
    # count 40 was on screen from 10.80 to 10.82; grabbed at 10.90: 100 ms after it came,
    # less the half period (its middle) and the display's lag
    assert meter.seen(40, 10.90) == pytest.approx(0.1 - 0.01 - 0.005)
    assert meter.seen(None, 10.9) is None
    assert meter.seen(99, 10.0) is None  # grabbed long before it was shown: refused
    for _ in range(9):
        meter.seen(40, 10.90)
    meter.seen(15, 10.90)  # a misread: 0.6 s off the others
    summary = meter.summary()
    assert (summary.samples, summary.misread, summary.unread) == (11, 1, 2)
    assert summary.mean_s == pytest.approx(0.085)
    assert "--camera-latency-ms 85" in summary.describe()
    empty = LatencyMeter(0.02).summary()
    assert empty.samples == 0
    assert math.isnan(empty.mean_s)
    assert "no latency measured" in empty.describe()
