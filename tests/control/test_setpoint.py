import math

import pytest

from perchpose.control import ControllerConfigError, SetpointLimits, safe_setpoint


def test_setpoints_within_limits_pass_unchanged() -> None:
    sp = safe_setpoint([0.1, -0.2, 0.3], 0.5, SetpointLimits())
    assert sp.v_mps == (0.1, -0.2, 0.3)
    assert sp.yaw_rate_rad_s == 0.5
    assert not sp.clamped
    assert not sp.replaced


def test_setpoints_are_clamped_keeping_the_horizontal_direction() -> None:
    limits = SetpointLimits(max_xy_mps=0.5, max_z_mps=0.3, max_yaw_rate_rad_s=1.0)
    sp = safe_setpoint([3.0, 4.0, -2.0], -7.0, limits)
    assert sp.v_mps == pytest.approx((0.3, 0.4, -0.3))
    assert sp.yaw_rate_rad_s == -1.0
    assert sp.clamped


@pytest.mark.parametrize(
    ("v", "yaw_rate"),
    [
        ([math.nan, 0.0, 0.1], 0.0),
        ([0.0, math.inf, 0.1], 0.0),
        ([0.0, 0.0, -math.inf], 0.0),
        ([0.1, 0.0, 0.1], math.nan),
        ([0.1, 0.0], 0.0),
    ],
)
def test_anything_non_finite_becomes_a_hover(v: list[float], yaw_rate: float) -> None:
    sp = safe_setpoint(v, yaw_rate, SetpointLimits())
    assert sp.replaced
    assert sp.v_mps == (0.0, 0.0, 0.0)
    assert sp.yaw_rate_rad_s == 0.0


def test_bad_limits_are_refused() -> None:
    with pytest.raises(ControllerConfigError, match="max_xy_mps"):
        SetpointLimits(max_xy_mps=0.0)
    with pytest.raises(ControllerConfigError, match="max_z_mps"):
        SetpointLimits(max_z_mps=math.inf)
