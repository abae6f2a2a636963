import numpy as np
import pytest

from perchpose.control.position_fix import PositionFixes, PositionFixSettings
from perchpose.errors import ControllerConfigError


def test_fixes_anchor_the_target_then_say_where_the_vehicle_is() -> None:
    fixes = PositionFixes(PositionFixSettings(anchor_fixes=3))
    p_now = np.array([1.0, 2.0, 1.5])
    for target in ([0.0, 0.0, 2.0], [0.02, 0.0, 2.0], [0.01, 0.03, 2.0]):
        assert fixes.fix(np.array(target), p_now) is None  # anchoring
    assert fixes.anchor_m == pytest.approx([0.01, 0.01, 2.0])
    # the target seems 4 cm further along x in the odometry frame: the odometry drifted 4 cm
    # the other way, so the vehicle is 4 cm behind where its odometry says
    p = fixes.fix(np.array([0.05, 0.01, 2.0]), p_now)
    assert p == pytest.approx([0.96, 2.0, 1.5])
    assert fixes.sent == 1


def test_an_outlier_is_not_sent_and_a_drift_beyond_it_anchors_again() -> None:
    fixes = PositionFixes(PositionFixSettings(anchor_fixes=1, max_jump_m=0.1, reanchor_after=3))
    p_now = np.zeros(3)
    fixes.fix(np.zeros(3), p_now)
    assert fixes.fix(np.array([0.2, 0.0, 0.0]), p_now) is None
    assert fixes.refused == 1
    assert fixes.fix(np.array([0.01, 0.0, 0.0]), p_now) is not None  # the count restarts
    for _ in range(3):
        assert fixes.fix(np.array([0.3, 0.0, 0.0]), p_now) is None
    assert fixes.anchor_m is None  # three in a row: the odometry drifted, anchor afresh
    fixes.fix(np.array([0.3, 0.0, 0.0]), p_now)
    assert fixes.fix(np.array([0.3, 0.0, 0.0]), p_now) == pytest.approx(np.zeros(3))


def test_a_height_apart_from_the_estimate_still_corrects_the_horizontal_position() -> None:
    # a range sensor and the camera disagree on the height by more than the horizontal gate:
    # the fix is sent, with the camera's height while it is within its own bound, and with the
    # estimate's own height beyond it
    fixes = PositionFixes(
        PositionFixSettings(anchor_fixes=1, max_jump_m=0.1, max_height_jump_m=0.3)
    )
    p_now = np.array([0.0, 0.0, 2.0])
    fixes.fix(np.zeros(3), p_now)
    near = fixes.fix(np.array([0.03, 0.0, 0.15]), p_now)
    assert near == pytest.approx([-0.03, 0.0, 1.85])
    far = fixes.fix(np.array([0.03, 0.0, 0.5]), p_now)
    assert far == pytest.approx([-0.03, 0.0, 2.0])
    assert fixes.refused == 0


def test_non_finite_input_and_bad_settings_are_refused() -> None:
    fixes = PositionFixes(PositionFixSettings(anchor_fixes=1))
    assert fixes.fix(np.array([np.nan, 0.0, 0.0]), np.zeros(3)) is None
    assert fixes.anchor_m is None
    with pytest.raises(ControllerConfigError, match="anchor_fixes"):
        PositionFixSettings(anchor_fixes=0)
    with pytest.raises(ControllerConfigError, match="std_m"):
        PositionFixSettings(std_m=0.0)
    with pytest.raises(ControllerConfigError, match="max_height_jump_m"):
        PositionFixSettings(max_height_jump_m=-0.1)
