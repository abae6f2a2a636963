import math

import numpy as np
import pytest

from perchpose.io.capture_clock import DeviceClock, StreamClock


def test_a_device_stamp_is_taken_where_it_can_be_the_capture() -> None:
    clock = DeviceClock()
    assert clock.stamp(99.97, 100.0) == 99.97
    # none (0), after the grab, too long before it (a driver on the wall clock), not a number
    for source_s in (0.0, None, 100.01, 98.5, math.nan, 1.8e9):
        assert math.isnan(clock.stamp(source_s, 100.0))
    assert clock.refused == 6


def test_a_stream_clock_takes_out_the_delay_that_varies() -> None:
    """Frames presented every 1/30 s on the sender's clock (which starts at 7 s) arrive after
    a delay of 80 ms plus up to 60 ms of network and decoder jitter: once a frame that came
    through fast has been seen, every stamp is its presentation time plus the smallest delay,
    so the stamps keep the sender's spacing; the grab times keep the jitter."""
    rng = np.random.default_rng(1)
    clock = StreamClock()
    pts_s = 7.0 + np.arange(300) / 30.0
    grabbed_s = 500.0 + np.arange(300) / 30.0 + 0.080 + rng.uniform(0.0, 0.060, 300)
    stamps = np.array([clock.stamp(p, g) for p, g in zip(pts_s, grabbed_s, strict=True)])
    assert np.all(stamps <= grabbed_s)
    smallest = float(np.min(grabbed_s - pts_s))
    settled = stamps[30:] - pts_s[30:]
    assert np.ptp(settled) < 0.003  # the smallest delay was (nearly) met in the first second
    assert np.allclose(settled, smallest, atol=0.003)
    assert np.std(grabbed_s - pts_s) > 0.015
    assert clock.refused == clock.restarts == 0


def test_a_stream_clock_follows_drift_and_restarts() -> None:
    clock = StreamClock(window_s=5.0)
    # the sender's clock runs 100 ppm slow: the delay grows 1 ms every 10 s; the window's
    # smallest delay follows it within the window's share
    for k in range(30 * 60):
        t_s = k / 30.0
        stamp = clock.stamp(t_s, 1000.0 + t_s * (1 + 1e-4) + 0.05)
        assert stamp == pytest.approx(1000.0 + t_s * (1 + 1e-4) + 0.05, abs=0.0006)
    # the sender restarts its presentation times at 0: a new mapping, and the next stamps
    # are its own
    assert clock.stamp(0.0, 1070.0) == pytest.approx(1070.0)
    assert clock.restarts == 1
    assert clock.stamp(1 / 30, 1070.0 + 1 / 30 + 0.01) == pytest.approx(1070.0 + 1 / 30)


def test_a_stream_frame_held_up_is_refused_and_a_clock_that_stops_starts_afresh() -> None:
    clock = StreamClock(restart_s=1.0)
    for k in range(30):
        clock.stamp(k / 30.0, 10.0 + k / 30.0)
    # a stall of 1.5 s, then the frames held up come in a burst: refused (their grab dates
    # them), and the mapping stays
    assert math.isnan(clock.stamp(1.0, 12.5))
    assert clock.stamp(1.0 + 1 / 30, 11.0 + 1 / 30 + 0.002) == pytest.approx(11.0 + 1 / 30)
    assert clock.refused == 1
    assert clock.restarts == 0
    # presentation times that stop moving on while frames come: after 1 s, a new mapping
    stuck = [clock.stamp(2.0, 14.0 + k / 30.0) for k in range(40)]
    assert all(math.isnan(s) for s in stuck[:30])
    assert clock.restarts == 1
    assert stuck[30] == pytest.approx(15.0)
    clock.reset()
    assert clock.stamp(5.0, 20.0) == 20.0
