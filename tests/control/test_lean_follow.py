"""The watch on attitude setpoints: a vehicle that flies the lean sent through its attitude
loop is never judged; one that takes an angle with the other sign is, on that angle."""

import math

import numpy as np
import pytest

from perchpose.control.lean_follow import LeanFollowWatch

DT_S = 0.02  # the pilot's setpoints at 50 Hz


def _fly(
    flip: tuple[float, float] = (1.0, 1.0),
    seconds: float = 4.0,
    response_s: float = 0.15,
    report_delay_s: float = 0.03,
    held: tuple[float, float] | None = None,
    seed: int = 0,
) -> tuple[LeanFollowWatch, float | None]:
    """Leans asked at random (a new one each 0.25 s, 8-18 deg either way) flown by an
    attitude loop of ``response_s`` that takes each angle times ``flip``, its attitude
    reported ``report_delay_s`` late; ``held``: from..to (s) the plate holds it level and
    the watch is told so. Gives the watch and when it judged (None: never)."""
    rng = np.random.default_rng(seed)
    watch = LeanFollowWatch(response_s=0.15, window_s=0.3, max_error_deg=10.0)
    lean = np.zeros(2)
    flown: list[np.ndarray] = []
    sent = np.zeros(2)
    for k in range(int(seconds / DT_S)):
        t_s = k * DT_S
        if k % int(0.25 / DT_S) == 0:
            size = rng.uniform(math.radians(8.0), math.radians(18.0), 2)
            sent = size * rng.choice([-1.0, 1.0], 2)
        on_plate = held is not None and held[0] <= t_s < held[1]
        alpha = 1.0 - math.exp(-DT_S / response_s)
        lean = np.zeros(2) if on_plate else lean + alpha * (sent * np.array(flip) - lean)
        flown.append(lean.copy())
        own = flown[max(0, k - round(report_delay_s / DT_S))]
        if watch.update(t_s, (sent[0], sent[1]), (own[0], own[1]), watch=not on_plate):
            return watch, t_s
    return watch, None


@pytest.mark.parametrize("seed", range(5))
def test_a_vehicle_that_flies_the_lean_sent_is_never_judged(seed: int) -> None:
    """Its loop a third slower than the watch assumes and its attitude reported 60 ms late:
    still within the watch's margin."""
    watch, judged = _fly(response_s=0.2, report_delay_s=0.06, seed=seed)
    assert judged is None
    assert watch.broken is None


@pytest.mark.parametrize(("flip", "axis"), [((1.0, -1.0), "pitch"), ((-1.0, 1.0), "roll")])
def test_an_angle_taken_with_the_other_sign_is_judged_within_a_second(
    flip: tuple[float, float], axis: str
) -> None:
    watch, judged = _fly(flip=flip)
    assert judged is not None
    assert judged < 1.0
    assert watch.broken == axis
    assert watch.detail.startswith(f"{axis} sent ")
    # judged once and for good
    assert watch.update(judged + DT_S, (0.0, 0.0), (0.0, 0.0)) == axis


def test_a_vehicle_the_plate_holds_level_is_not_judged() -> None:
    """On the plate for 2 s, leans still asked: the plate, not a sign, keeps the vehicle
    level, and the watch starts again when it leaves."""
    _, judged = _fly(held=(1.0, 3.0))
    assert judged is None


def test_an_unknown_attitude_is_not_judged_and_starts_the_watch_again() -> None:
    watch = LeanFollowWatch(response_s=0.15, window_s=0.3, max_error_deg=10.0)
    far = (math.radians(15.0), 0.0)
    for k in range(10):  # 0.18 s apart by over 10 deg, then an unknown attitude
        watch.update(0.02 * k, far, (-far[0], 0.0))
    watch.update(0.2, far, (math.nan, 0.0))
    for k in range(14):  # 0.26 s apart again: not yet the window
        assert watch.update(0.22 + 0.02 * k, far, (-far[0], 0.0)) is None
