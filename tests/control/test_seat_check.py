"""The check of the magnet's hold before the motors stop: held once the window is spanned
without a fall; dropped on the accelerometer's fall or the height's."""

import math

import pytest

from perchpose.control.seat_check import SeatCheck, SeatVerdict

LIMITS = (0.4, 0.06, 6.0)  # window_s, drop_m, fall_mps2
G = 9.81


def _judged(heights: list[float | None], forces: list[float | None]) -> tuple[float, SeatVerdict]:
    """The time and verdict of a check begun at t = 0 at 2 m, sampled at 50 Hz."""
    check = SeatCheck(0.0, 2.0, "the final climb stopped against the plate")
    for i, (height, force) in enumerate(zip(heights, forces, strict=True)):
        verdict = check.verdict(i * 0.02, height, force, LIMITS)
        if verdict is not None:
            return i * 0.02, verdict
    raise AssertionError("no verdict")


def test_a_vehicle_that_stays_is_held_once_the_window_is_spanned() -> None:
    """Its height wanders 4 cm (a Flow deck's filter 2 m up) and its accelerometer reads g
    with noise: held at 0.4 s, not before."""
    heights = [2.0 - 0.04 * math.sin(i / 5.0) ** 2 for i in range(40)]
    forces: list[float | None] = [G + 0.3 * (-1) ** i for i in range(40)]
    t_s, verdict = _judged(list(heights), forces)
    assert verdict == SeatVerdict.HELD
    assert t_s == pytest.approx(0.4)


def test_an_accelerometer_that_reads_a_fall_twice_running_is_a_drop() -> None:
    """Let go on a quarter of its hover thrust, it reads a quarter of g: dropped on the second
    such reading, before the height moved; one reading alone (a knock) is not a fall."""
    forces: list[float | None] = [G] * 5 + [2.5] + [G] * 5 + [2.5, 2.5] + [G] * 27
    t_s, verdict = _judged([2.0] * 40, forces)
    assert verdict == SeatVerdict.DROPPED
    assert t_s == pytest.approx(12 * 0.02)


def test_without_an_accelerometer_the_height_decides() -> None:
    heights: list[float | None] = [2.0 - max(0, i - 5) * 0.025 for i in range(40)]
    t_s, verdict = _judged(heights, [None] * 40)
    assert verdict == SeatVerdict.DROPPED
    assert t_s == pytest.approx(8 * 0.02)  # 7.5 cm down; 5 cm the sample before


def test_no_verdict_without_a_live_height_and_the_first_live_one_is_the_start() -> None:
    """No height at the start (none is live): the check waits; the first live one is where
    it begins, so a vehicle at 1.5 m by then is not read as having dropped 50 cm."""
    check = SeatCheck(0.0, None, "held")
    assert check.verdict(0.1, None, None, LIMITS) is None
    assert check.verdict(0.2, 1.5, None, LIMITS) is None
    assert check.verdict(0.3, 1.49, None, LIMITS) is None
    assert check.verdict(0.45, 1.5, None, LIMITS) == SeatVerdict.HELD
    assert check.drop_m == pytest.approx(0.01)
