import math

import numpy as np
import pytest

from perchpose.control.attitude_command import LeanLoop, lean_for
from perchpose.geometry import leaned

MAX = math.radians(20.0)


def test_no_acceleration_is_level() -> None:
    lean = lean_for([0.0, 0.0], 1.2, MAX)
    assert (lean.roll_rad, lean.pitch_rad, lean.clamped) == (0.0, 0.0, False)


@pytest.mark.parametrize(
    ("a_world", "yaw_deg", "roll_sign", "pitch_sign"),
    [
        ((1.0, 0.0), 0.0, 0, 1),  # forward: nose down
        ((0.0, 1.0), 0.0, -1, 0),  # to the left: left side down
        ((1.0, 0.0), 90.0, 1, 0),  # world x is to the right of a heading along y
        ((-1.0, 0.0), 180.0, 0, 1),  # world -x is forward when heading along -x
    ],
)
def test_the_lean_points_the_thrust_where_the_acceleration_is_asked(
    a_world: tuple[float, float], yaw_deg: float, roll_sign: int, pitch_sign: int
) -> None:
    """Roll and pitch are the body's ZYX angles under its heading (pitch positive nose down,
    roll positive right side down), and the vehicle at that lean accelerates as asked."""
    yaw = math.radians(yaw_deg)
    lean = lean_for(a_world, yaw, MAX)
    assert np.sign(round(lean.roll_rad, 12)) == roll_sign
    assert np.sign(round(lean.pitch_rad, 12)) == pitch_sign
    np.testing.assert_allclose(
        9.81 * np.array(leaned(lean.roll_rad, lean.pitch_rad, yaw)), a_world, atol=1e-12
    )


def test_an_acceleration_past_the_largest_lean_is_cut_along_its_direction() -> None:
    lean = lean_for([30.0, -40.0], 0.3, MAX)
    assert lean.clamped
    a = 9.81 * np.array(leaned(lean.roll_rad, lean.pitch_rad, 0.3))
    assert np.linalg.norm(a) == pytest.approx(9.81 * math.tan(MAX))
    np.testing.assert_allclose(a / np.linalg.norm(a), [0.6, -0.8], atol=1e-12)


def test_the_loop_leans_on_the_velocity_error_against_the_push() -> None:
    """``gain (v_asked - v) - push``: at the velocity asked, the lean holds the push off; the
    push is low-passed after its first sample, and a missing or non-finite one counts as
    none."""
    loop = LeanLoop(5.0, MAX, push_filter_s=0.03)
    held = loop.lean(0.0, [0.2, 0.0], [0.2, 0.0], [1.0, 0.0], 0.0)
    assert 9.81 * math.tan(held.pitch_rad) == pytest.approx(-1.0)
    stepped = loop.lean(0.01, [0.2, 0.0], [0.2, 0.0], [2.0, 0.0], 0.0)
    push = 1.0 + (1.0 - math.exp(-0.01 / 0.03))
    assert 9.81 * math.tan(stepped.pitch_rad) == pytest.approx(-push)
    moving = loop.lean(0.02, [0.2, 0.0], [0.0, 0.1], None, 0.0)
    a = 9.81 * np.array(leaned(moving.roll_rad, moving.pitch_rad, 0.0))
    np.testing.assert_allclose(a, [1.0, -0.5], atol=1e-12)
    nan = loop.lean(0.03, [0.0, 0.0], [0.0, 0.0], [math.nan, 0.0], 0.0)
    assert (nan.roll_rad, nan.pitch_rad) == (0.0, 0.0)
    off = LeanLoop(5.0, MAX, push_feedforward=False).lean(
        0.0, [0.0, 0.0], [0.0, 0.0], [1.0, 0.0], 0.0
    )
    assert (off.roll_rad, off.pitch_rad) == (0.0, 0.0)


def test_the_velocity_is_carried_forward_by_the_acceleration_the_vehicle_has_now() -> None:
    """A velocity ``v_age_s`` old is carried over that age and ``lead_s`` more by the lean's
    acceleration now and the push; without an acceleration now it is taken as it is."""
    loop = LeanLoop(8.0, MAX, push_filter_s=0.0, lead_s=0.04)
    lean = loop.lean(0.0, [0.3, 0.0], [0.3, 0.0], [0.5, 0.0], 0.0, 0.02, [1.0, 0.0])
    carried = 0.3 + (1.0 + 0.5) * 0.06
    expected = 8.0 * (0.3 - carried) - 0.5
    assert 9.81 * math.tan(lean.pitch_rad) == pytest.approx(expected)
    as_it_is = loop.lean(0.01, [0.3, 0.0], [0.3, 0.0], [0.5, 0.0], 0.0, 0.02, None)
    assert 9.81 * math.tan(as_it_is.pitch_rad) == pytest.approx(-0.5)
