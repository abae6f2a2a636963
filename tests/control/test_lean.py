import math

import numpy as np
import pytest

from perchpose.control.lean import GRAVITY_MPS2, LeanCorrection
from perchpose.errors import ControllerConfigError
from perchpose.geometry import rot_y, rot_z


def _fly(
    lean: LeanCorrection, R: np.ndarray, f_body: np.ndarray | None, seconds: float
) -> np.ndarray:
    corrected = R
    for k in range(int(seconds / 0.01) + 1):
        corrected = lean.correct(R, f_body, k * 0.01)
    return corrected


def test_a_steady_push_leans_the_attitude_against_it_by_push_over_g() -> None:
    # the estimate says level; the accelerometer says 1 m/s^2 of push along world x
    corrected = _fly(
        LeanCorrection(1.2, offset_mps2=0.0), np.eye(3), np.array([1.0, 0.0, GRAVITY_MPS2]), 12.0
    )
    z_body = corrected[:, 2]
    # the thrust leans into the wind: against the push, by push / g
    assert z_body[0] == pytest.approx(-math.sin(1.0 / GRAVITY_MPS2), abs=1e-4)
    assert z_body[1] == pytest.approx(0.0, abs=1e-9)


def test_the_lean_builds_over_its_lag() -> None:
    lean = LeanCorrection(1.0, offset_mps2=0.0)
    lean.correct(np.eye(3), np.array([0.0, 0.0, GRAVITY_MPS2]), -0.01)  # taken over in still air
    _fly(lean, np.eye(3), np.array([0.0, 2.0, GRAVITY_MPS2]), 1.0)
    built = lean.lean_rad[0] / (2.0 / GRAVITY_MPS2)
    assert built == pytest.approx(1.0 - math.exp(-1.0), abs=0.02)


def test_the_first_push_is_taken_as_steady() -> None:
    # the pilot takes over a vehicle that has hovered in a wind: its filter's tilt is already
    # off by the whole lean, and so is the correction from the first sample on
    lean = LeanCorrection(1.0, offset_mps2=0.0)
    lean.correct(np.eye(3), np.array([0.0, 2.0, GRAVITY_MPS2]), 5.0)
    assert lean.lean_rad[0] == pytest.approx(2.0 / GRAVITY_MPS2, rel=1e-9)


def test_the_push_is_turned_into_the_world_by_the_heading() -> None:
    # heading 90 degrees: the body's x is the world's y
    corrected = _fly(
        LeanCorrection(0.5, offset_mps2=0.0), rot_z(math.pi / 2), np.array([1.0, 0.0, 9.81]), 8.0
    )
    z_body = corrected[:, 2]
    assert z_body[1] == pytest.approx(-math.sin(1.0 / GRAVITY_MPS2), abs=1e-4)
    assert z_body[0] == pytest.approx(0.0, abs=1e-6)


def test_a_push_within_the_accelerometers_offset_is_no_lean_and_beyond_it_the_excess_is() -> None:
    offset = np.array([0.08, -0.05, GRAVITY_MPS2])  # what a still vehicle's offset reads
    lean = LeanCorrection(0.5, offset_mps2=0.1)
    _fly(lean, np.eye(3), offset, 6.0)
    np.testing.assert_allclose(lean.lean_rad, 0.0, atol=1e-12)
    _fly(lean, np.eye(3), np.array([0.0, 1.1, GRAVITY_MPS2]), 12.0)
    assert lean.lean_rad[0] == pytest.approx(1.0 / GRAVITY_MPS2, rel=1e-4)


def test_without_a_push_the_model_holds_what_it_had() -> None:
    lean = LeanCorrection(1.0)
    _fly(lean, np.eye(3), np.array([1.0, 0.0, 9.81]), 2.0)
    held = lean.lean_rad.copy()
    lean.correct(np.eye(3), None, 3.0)
    lean.correct(np.eye(3), np.array([np.nan, 0.0, 9.81]), 4.0)
    np.testing.assert_allclose(lean.lean_rad, held)


def test_a_corrected_attitude_stays_a_rotation() -> None:
    corrected = _fly(LeanCorrection(0.3), rot_y(0.2) @ rot_z(1.0), np.array([3.0, -2.0, 9.0]), 3.0)
    np.testing.assert_allclose(corrected @ corrected.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(corrected) == pytest.approx(1.0)


@pytest.mark.parametrize("lag_s", [0.0, -1.0, math.nan])
def test_a_lag_that_is_not_positive_is_refused(lag_s: float) -> None:
    with pytest.raises(ControllerConfigError, match="lag_s"):
        LeanCorrection(lag_s)
    with pytest.raises(ControllerConfigError, match="offset_mps2"):
        LeanCorrection(1.0, offset_mps2=lag_s if lag_s != 0 else -0.1)
