"""The inertial filter: the vehicle's true velocity from late fixes and the accelerometer,
and what its own velocity estimate is off by."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from perchpose.control.inertial import InertialSettings, InertialTracker
from perchpose.errors import ControllerConfigError

Array = NDArray[np.float64]
ODOMETRY_HZ = 100.0
CAMERA_HZ = 30.0
LATENCY_S = 0.1  # the fixes' latency
DURATION_S = 8.0


def flight(
    seed: int,
    *,
    error_mps: float,
    error_s: float,
    white_mps: float = 0.0,
    accel_noise_mps2: float = 0.2,
    accel_bias_mps2: float = 0.08,
    known_correlated: bool = False,
) -> tuple[InertialTracker, dict[str, list[float]]]:
    """A vehicle swaying along x and y (sines of a few cm), an odometry velocity with a
    correlated error (first order, ``error_s``) and white noise, an accelerometer with noise
    and a bias, fixes of its position (0.5 mm of noise) ``LATENCY_S`` late. Returns the
    filter and, per odometry sample after the first 3 s, the odometry's velocity error and
    the filter's (x axis), and the correlated error against the filter's estimate of it.
    ``known_correlated``: the filter is told the error is correlated (``assume_correlated``)."""
    rng = np.random.default_rng(seed)
    tracker = InertialTracker()
    if known_correlated:
        tracker.assume_correlated()
    dt = 1.0 / ODOMETRY_HZ
    decay = math.exp(-dt / error_s)
    e = np.zeros(2)
    fixes: list[tuple[float, float, Array]] = []  # (arrival, capture, position)
    out: dict[str, list[float]] = {"odometry": [], "filter": [], "error": [], "estimate": []}
    out["unused"] = []
    next_frame = 0.0
    for k in range(int(DURATION_S * ODOMETRY_HZ)):
        t = k * dt
        w = np.array([2.1, 1.3])
        p = np.array([0.03 * math.sin(w[0] * t), 0.02 * math.sin(w[1] * t + 1.0)])
        v = np.array([0.03 * w[0] * math.cos(w[0] * t), 0.02 * w[1] * math.cos(w[1] * t + 1.0)])
        a = -(w**2) * p
        e = decay * e + error_mps * math.sqrt(1.0 - decay * decay) * rng.normal(size=2)
        v_odometry = v + e + white_mps * rng.normal(size=2)
        a_read = a + accel_bias_mps2 + accel_noise_mps2 * rng.normal(size=2)
        tracker.sample(t, a_read, v_odometry)
        if t >= next_frame:
            fixes.append((t + LATENCY_S, t, p + 0.0005 * rng.normal(size=2)))
            next_frame += 1.0 / CAMERA_HZ
        while fixes and fixes[0][0] <= t:
            _, captured, r = fixes.pop(0)
            tracker.fix(captured, r, 0.3)
        if t >= 3.0:
            state = tracker.state_at(t)
            estimate = tracker.odometry_error(t)
            if state is None or estimate is None:
                out["unused"].append(t)
                continue
            out["odometry"].append(float(v_odometry[0] - v[0]))
            out["filter"].append(float(state[1][0] - v[0]))
            out["error"].append(float(e[0]))
            out["estimate"].append(float(estimate[0]))
    return tracker, out


def rms(values: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def test_a_correlated_odometry_error_is_seen_through_and_estimated() -> None:
    """A Flow deck's error at 2 m (6 cm/s over 0.15 s): the filter's velocity is off by under
    a third of that, and its estimate of the error takes out most of it."""
    tracker, out = flight(0, error_mps=0.06, error_s=0.15)
    assert rms(out["odometry"]) > 0.04
    assert rms(out["filter"]) < rms(out["odometry"]) / 3
    residual = np.subtract(out["error"], out["estimate"])
    assert rms(list(residual)) < 0.5 * rms(out["error"])
    assert tracker.error_var > 0.03**2  # learnt as correlated
    assert not out["unused"]
    assert tracker.resets == 0


def test_a_white_odometry_error_is_learnt_as_white() -> None:
    """White noise (3 cm/s per sample) is no error to correct (the vehicle's loop averages
    it): its correlated share is learnt near the floor, and the filter is not used."""
    tracker, out = flight(1, error_mps=0.0, error_s=0.15, white_mps=0.03)
    assert tracker.error_var < 0.015**2
    assert not tracker.in_use
    assert tracker.ready  # it knows the velocity; it is only not worth using
    assert not out["filter"]
    assert tracker.state_at(8.0) is None


def test_a_small_error_known_to_be_correlated_is_corrected() -> None:
    """A Kalman filter's velocity in still air: 1.5 cm/s off, over 0.2 s. Learnt, it is too
    small to use the filter for; told that it is correlated, the filter is used from its first
    fixes and its velocity is off by less than the odometry's."""
    learnt, out = flight(2, error_mps=0.015, error_s=0.2)
    assert not learnt.in_use
    assert not out["filter"]
    told, out = flight(2, error_mps=0.015, error_s=0.2, known_correlated=True)
    assert told.in_use
    assert not out["unused"]
    assert rms(out["filter"]) < 0.8 * rms(out["odometry"])  # 0.58-0.8 on seeds 0-7
    assert math.sqrt(told.error_var) < told.settings.use_above_mps  # its size still learnt


def test_nothing_is_said_before_the_first_fixes() -> None:
    tracker = InertialTracker()
    for k in range(20):
        tracker.sample(k * 0.01, np.zeros(2), np.zeros(2))
    assert not tracker.ready
    assert tracker.state_at(0.2) is None
    assert tracker.odometry_error(0.2) is None
    assert tracker.velocity_at(0.19) is None


def test_a_late_fix_is_replayed_from_its_capture_time() -> None:
    """A fix given 50 ms late, after the samples that followed its capture, leaves the state
    the same fix leaves given at its capture (the filter is linear; only the slow learning of
    the odometry's error sees the order)."""
    settings = InertialSettings(use_above_mps=1e-6, use_below_mps=1e-6)  # always in use

    def run_pairs(late: bool) -> Array:
        tracker = InertialTracker(settings)
        rng = np.random.default_rng(5)
        pending: list[tuple[float, float]] = []
        for k in range(60):
            t = k * 0.01
            tracker.sample(t, rng.normal(0, 0.1, 2), rng.normal(0, 0.02, 2))
            if k % 3 == 0 and t <= 0.5:
                pending.append((t + (0.05 if late else 0.0), t))
            while pending and pending[0][0] <= t + 1e-9:
                _, captured = pending.pop(0)
                tracker.fix(captured, np.array([0.01, -0.02]), 0.3)
        state = tracker.state_at(0.6)
        assert state is not None
        return np.concatenate(state)

    on_time = run_pairs(late=False)
    late = run_pairs(late=True)
    np.testing.assert_allclose(late, on_time, atol=2e-3)


def test_a_fix_far_from_the_prediction_starts_afresh() -> None:
    """The camera finds the target again 20 cm from where the filter had it: it restarts
    there rather than dragging its estimate across."""
    tracker = InertialTracker()
    for k in range(100):
        t = k * 0.01
        tracker.sample(t, np.zeros(2), np.zeros(2))
        if k % 3 == 0:
            tracker.fix(t, np.zeros(2), 0.3)
    assert tracker.ready
    tracker.sample(1.0, np.zeros(2), np.zeros(2))
    tracker.fix(1.0, np.array([0.2, 0.0]), 0.3)
    assert tracker.resets == 1
    assert not tracker.ready  # its velocity is no longer known
    assert tracker.odometry_error(1.0) is None


def test_a_blind_spell_keeps_a_ready_filter_in_use_until_its_velocity_is_lost() -> None:
    """Fixes stop (the camera too close to the plate to see): the velocity's spread grows
    past the spread the filter became ready at, and it stays in use, until the spread passes
    ``keep_velocity_std_mps``."""
    # always worth using; the odometry's error large and slow (a drag-free filter's), so
    # without fixes the velocity is soon not known
    settings = InertialSettings(
        use_above_mps=1e-6,
        use_below_mps=1e-6,
        min_odometry_error_mps=0.15,
        max_odometry_error_mps=0.3,
        odometry_error_s=1.0,
    )
    tracker = InertialTracker(settings)
    rng = np.random.default_rng(3)
    t = 0.0
    for k in range(200):  # 2 s of fixes at 33 Hz
        t = k * 0.01
        tracker.sample(t, rng.normal(0, 0.05, 2), rng.normal(0, 0.05, 2))
        if k % 3 == 0:
            tracker.fix(t, np.zeros(2), 0.3)
    assert tracker.in_use
    spreads, used = [], []
    for k in range(1, 801):  # 8 s blind
        tracker.sample(t + k * 0.01, rng.normal(0, 0.05, 2), rng.normal(0, 0.05, 2))
        spreads.append(math.sqrt(float(tracker._steps[-1].P[1, 1])))
        used.append(tracker.in_use)
    spread, in_use = np.array(spreads), np.array(used)
    between = (spread > settings.ready_velocity_std_mps) & (spread < settings.keep_velocity_std_mps)
    assert between.any()  # the blind spell did pass the ready spread
    assert in_use[between].all()
    assert not in_use[spread > settings.keep_velocity_std_mps].any()
    assert (spread > settings.keep_velocity_std_mps).any()


def test_settings_are_checked() -> None:
    with pytest.raises(ControllerConfigError, match="accel_noise_mps2"):
        InertialSettings(accel_noise_mps2=0.0)
    with pytest.raises(ControllerConfigError, match="fix_std_per_m"):
        InertialSettings(fix_std_per_m=-1.0)
    with pytest.raises(ControllerConfigError, match="keep_velocity_std_mps"):
        InertialSettings(keep_velocity_std_mps=0.01)
