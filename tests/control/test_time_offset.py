import math

import numpy as np
import pytest

from perchpose.control.time_offset import TimeOffset, TimeOffsetEstimator, TimeOffsetSettings
from perchpose.errors import ControllerConfigError
from perchpose.geometry import rot_x, rot_y, rot_z

P_WORLD_TARGET_M = np.array([0.1, -0.05, 0.0])


def R_world_body(t_s: float, sway: float = 1.0) -> np.ndarray:
    """A vehicle turning slowly and rocking by a few degrees, as one holding in wind does."""
    roll = sway * 0.05 * math.sin(2 * math.pi * 1.3 * t_s)
    pitch = sway * 0.04 * math.sin(2 * math.pi * 0.9 * t_s + 1.0)
    return rot_z(0.3 + 0.05 * t_s) @ rot_x(roll) @ rot_y(pitch)


def p_world_m(t_s: float, sway: float = 1.0) -> np.ndarray:
    """Climbing towards the target at 0.2 m/s, swaying by a few centimetres."""
    return np.array(
        [
            sway * 0.05 * math.sin(2 * math.pi * 0.5 * t_s),
            sway * 0.03 * math.cos(2 * math.pi * 0.7 * t_s),
            -1.5 + 0.2 * t_s,
        ]
    )


def fly(
    offset_s: float,
    *,
    sway: float = 1.0,
    noise_m: float = 0.001,
    duration_s: float = 5.0,
    seed: int = 0,
    settings: TimeOffsetSettings | None = None,
) -> TimeOffsetEstimator:
    """A flight with the vehicle's samples at 100 Hz and fixes at 30 fps, each stamped
    ``offset_s`` before its true capture time and handed over 150 ms after it."""
    rng = np.random.default_rng(seed)
    estimator = TimeOffsetEstimator(settings)
    captures = np.arange(0.2, duration_s, 1.0 / 30.0)
    k = 0
    for t in np.arange(0.0, duration_s + 0.5, 0.01):
        estimator.attitude(float(t), R_world_body(float(t), sway))
        estimator.position(float(t), p_world_m(float(t), sway))
        while k < captures.size and captures[k] + 0.15 <= t:
            c = float(captures[k])
            body = R_world_body(c, sway).T @ (P_WORLD_TARGET_M - p_world_m(c, sway))
            estimator.fix(c - offset_s, body + rng.normal(0.0, noise_m, 3))
            k += 1
    return estimator


@pytest.mark.parametrize("offset_s", [0.04, -0.025, 0.0, 0.11])
def test_finds_the_offset_from_the_motion(offset_s: float) -> None:
    e = fly(offset_s).latest
    assert e is not None
    assert e.offset_s == pytest.approx(offset_s, abs=0.002)
    assert abs(e.offset_s - offset_s) < 4.0 * e.sigma_s + 0.0005
    assert e.sigma_s < 0.005
    # the window's fixes, less the newest, whose search range the samples do not cover yet
    assert 2.5 < e.to_s - e.from_s <= 3.0


def test_correction_only_once_sure() -> None:
    sure = fly(0.04)
    assert sure.correction_s == pytest.approx(0.04, abs=0.002)
    # noisy fixes of a vehicle that barely moves: the cost is flat, nothing is corrected
    unsure = fly(0.04, sway=0.02, noise_m=0.005)
    assert unsure.latest is None or unsure.latest.sigma_s > 0.005
    assert unsure.correction_s == 0.0


def test_spread_is_honest_over_seeds() -> None:
    """The stated spread covers the error: over 20 noisy flights, errors beyond 3 sigma are
    rare (none expected)."""
    z = []
    for seed in range(20):
        e = fly(0.06, noise_m=0.004, seed=seed).latest
        assert e is not None
        z.append((e.offset_s - 0.06) / e.sigma_s)
    assert max(abs(v) for v in z) < 3.5
    assert 0.3 < float(np.std(z)) < 2.0


def test_no_estimate_without_enough_fixes() -> None:
    assert fly(0.04, duration_s=0.6).latest is None  # under min_span_s of fixes
    short = TimeOffsetSettings(min_fixes=500)
    assert fly(0.04, settings=short).latest is None


def test_an_offset_beyond_the_search_gives_no_estimate() -> None:
    narrow = TimeOffsetSettings(max_offset_s=0.05)
    assert fly(0.12, settings=narrow).latest is None


def test_out_of_order_and_non_finite_input_is_ignored() -> None:
    estimator = TimeOffsetEstimator()
    estimator.attitude(1.0, np.eye(3))
    estimator.attitude(0.5, np.eye(3))  # older than the last: dropped
    estimator.attitude(2.0, np.full((3, 3), math.nan))
    estimator.position(1.0, np.zeros(3))
    estimator.position(1.0, np.ones(3))  # repeated time: dropped
    assert estimator.fix(1.0, np.array([0.0, 0.0, 1.0])) is None
    assert estimator.fix(0.9, np.array([0.0, 0.0, 1.0])) is None
    assert estimator.fix(math.nan, np.array([0.0, 0.0, 1.0])) is None
    assert estimator.fix(1.1, np.array([math.inf, 0.0, 1.0])) is None
    assert estimator.latest is None


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"window_s": 0.0}, "window_s must be positive"),
        ({"grid_step_s": math.nan}, "grid_step_s must be positive"),
        ({"grid_step_s": 0.2}, "must not exceed max_offset_s"),
        ({"min_fixes": 3}, "min_fixes must be >= 8"),
        ({"every_fixes": 0}, "every_fixes >= 1"),
    ],
)
def test_bad_settings(settings: dict[str, float], message: str) -> None:
    with pytest.raises(ControllerConfigError, match=message):
        TimeOffsetSettings(**settings)  # type: ignore[arg-type]


def test_an_estimate_in_words() -> None:
    early = TimeOffset(-0.0804, 0.0015, 90, 0.0, 3.0, 3.0)
    said = "frames captured 80 ms before their stamps (+- 1.5 ms, from 90 fixes)"
    assert early.describe() == said
    late = TimeOffset(0.03, 0.002, 40, 0.0, 3.0, 3.0)
    assert late.describe().startswith("frames captured 30 ms after their stamps")
