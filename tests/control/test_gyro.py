import math

import cv2
import numpy as np
import pytest

from perchpose.control.gyro import MAX_GAP_S, BlendedAttitude, GyroAttitude, GyroReading
from perchpose.errors import ControllerConfigError
from perchpose.geometry import roll_pitch_rad, rot_x, rot_z


def _exp(rotvec: list[float] | np.ndarray) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(rotvec, np.float64).reshape(3, 1))
    return np.asarray(R)


def _rotvec_deg(R: np.ndarray) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(R)
    return np.degrees(rvec.reshape(3))


def _angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    rvec, _ = cv2.Rodrigues(A.T @ B)
    return math.degrees(float(np.linalg.norm(rvec)))


def test_a_steady_rate_integrates_to_its_angle() -> None:
    gyro = GyroAttitude()
    assert gyro.reading() is None
    for k in range(51):  # 1 s at 50 Hz, 0.5 rad/s about z then about the body's x
        gyro.add(k / 50, np.array([0.0, 0.0, 0.5]))
    reading = gyro.reading()
    assert reading is not None
    np.testing.assert_allclose(reading.R_ref_body, rot_z(0.5), atol=1e-9)
    for k in range(51, 76):
        gyro.add(k / 50, np.array([0.2, 0.0, 0.0]))
    # the interval where the rate changed at the mean of its ends, then 24 at 0.2 rad/s
    mixed = _exp(0.5 * np.array([0.2, 0.0, 0.5]) / 50)
    np.testing.assert_allclose(
        gyro.R_ref_body, rot_z(0.5) @ mixed @ rot_x(0.2 * 24 / 50), atol=1e-9
    )
    assert gyro.restarts == 0


def test_a_gap_is_not_integrated_across_and_is_counted() -> None:
    gyro = GyroAttitude()
    gyro.add(0.0, np.array([0.0, 0.0, 1.0]))
    gyro.add(0.02, np.array([0.0, 0.0, 1.0]))
    before = gyro.R_ref_body.copy()
    gyro.add(0.02 + 2 * MAX_GAP_S, np.array([0.0, 0.0, 1.0]))  # a stalled log
    np.testing.assert_allclose(gyro.R_ref_body, before)
    assert gyro.restarts == 1
    gyro.add(0.5, np.array([math.nan, 0.0, 0.0]))  # a bad sample is dropped
    gyro.add(0.1, np.array([0.0, 0.0, 1.0]))  # one out of order too
    np.testing.assert_allclose(gyro.R_ref_body, before)


def test_the_blend_keeps_the_gyro_over_seconds_and_the_estimate_beyond() -> None:
    """An estimate whose tilt wanders by 1 degree at 1 Hz (a filter's corrections), a gyro
    with a bias of 0.1 deg/s in a frame of its own: the blended attitude is off by a near
    constant (the bias over the blend time), and what changes of its error is under a fifth
    of the estimate's; a steady offset of the estimate (what the gyro cannot know) is taken
    within 5 % after five blend times."""
    blend_s = 3.0
    blend = BlendedAttitude(blend_s)
    gyro = GyroAttitude()  # its frame is the body's at the start, rot_z(0.5) off the world
    bias = np.radians([0.1, -0.1, 0.0])
    dt = 0.02
    errors_est, errors_blend = [], []
    R_before = None
    for k in range(round(30 / dt)):
        t = k * dt
        R_true = rot_z(0.5) @ rot_x(0.1 * math.sin(0.7 * t))
        rate = np.zeros(3) if R_before is None else np.radians(_rotvec_deg(R_before.T @ R_true))
        gyro.add(t, rate / dt + bias)
        R_before = R_true
        wobble = _exp([math.radians(1.0) * math.sin(2 * math.pi * t), 0.0, 0.0])
        R_est = R_true @ wobble
        reading = gyro.reading()
        assert reading is not None
        R = blend.blend(R_est, reading, t)
        if t > 15.0:  # five blend times in
            errors_est.append(_rotvec_deg(R_true.T @ R_est))
            errors_blend.append(_rotvec_deg(R_true.T @ R))
    est, blended = np.array(errors_est), np.array(errors_blend)
    offset = np.linalg.norm(blended.mean(axis=0))
    assert offset == pytest.approx(math.degrees(np.linalg.norm(bias)) * blend_s, rel=0.15)
    varying = math.sqrt(float(np.mean(np.sum((blended - blended.mean(axis=0)) ** 2, axis=1))))
    assert varying < 0.2 * math.sqrt(float(np.mean(np.sum(est**2, axis=1))))

    steady = BlendedAttitude(blend_s)
    offset = rot_x(math.radians(2.0))
    first = steady.blend(offset, GyroReading(np.eye(3), 0), 0.0)
    np.testing.assert_allclose(first, offset)  # the first reading takes the estimate's word
    steady.blend(np.eye(3), GyroReading(np.eye(3), 0), 0.0)
    for k in range(1, round(5 * blend_s / dt) + 1):
        R = steady.blend(offset, GyroReading(np.eye(3), 0), k * dt)
    assert abs(math.degrees(roll_pitch_rad(R)[0]) - 2.0) < 0.05 * 2.0


def test_a_restarted_integral_is_taken_afresh_from_the_estimate() -> None:
    blend = BlendedAttitude(3.0)
    blend.blend(np.eye(3), GyroReading(np.eye(3), 0), 0.0)
    tilted = rot_x(math.radians(3.0))
    held = blend.blend(tilted, GyroReading(np.eye(3), 0), 0.02)
    assert _angle_deg(held, np.eye(3)) < 0.1  # the gyro says nothing turned
    afresh = blend.blend(tilted, GyroReading(rot_z(0.4), 1), 0.04)
    np.testing.assert_allclose(afresh, tilted, atol=1e-12)
    with pytest.raises(ControllerConfigError, match="blend_s must be positive"):
        BlendedAttitude(0.0)
