"""The compiled plumb_bob model against OpenCV's projectPoints and undistortPoints."""

import cv2
import numpy as np
import pytest

from perchpose.camera import CameraModel, plumb_bob

K = np.array([[520.0, 0.0, 318.0], [0.0, 515.0, 244.0], [0.0, 0.0, 1.0]])
COEFFICIENTS = {
    4: np.array([-0.21, 0.07, 0.001, -0.0015]),
    5: np.array([-0.28, 0.11, 0.0008, -0.0012, -0.02]),
    8: np.array([0.35, -0.12, 0.0005, 0.0009, 0.02, 0.62, -0.05, 0.03]),
    12: np.array([-0.2, 0.05, 0.001, -0.001, 0.0, 0.01, 0.0, 0.0, 0.002, -0.001, 0.0015, 0.0005]),
    # a tilted sensor: tau_x, tau_y (rad) last
    14: np.array([-0.28, 0.11, 0.0008, -0.0012, -0.02, 0, 0, 0, 0, 0, 0, 0, 0.01, -0.02]),
}


def points(rng: np.random.Generator, n: int = 200) -> np.ndarray:
    """Camera-frame points over most of a 640 x 480 view, 0.2-3 m away."""
    z = rng.uniform(0.2, 3.0, n)
    x = rng.uniform(-0.5, 0.5, n) * z
    y = rng.uniform(-0.38, 0.38, n) * z
    return np.stack([x, y, z], axis=1)


@pytest.mark.parametrize("length", sorted(COEFFICIENTS))
def test_the_projection_and_its_jacobian_are_opencvs(length: int) -> None:
    dist = COEFFICIENTS[length]
    p = points(np.random.default_rng(length))
    uv, duv_dq, in_front = plumb_bob.project_with_jacobian(p, K, plumb_bob.padded(dist))
    assert in_front.all()
    expected, jac = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    np.testing.assert_allclose(uv, expected.reshape(-1, 2), atol=1e-9)
    np.testing.assert_allclose(duv_dq, jac[:, 3:6].reshape(-1, 2, 3), rtol=1e-7, atol=1e-6)


@pytest.mark.parametrize("length", sorted(COEFFICIENTS))
def test_the_inverse_is_opencvs(length: int) -> None:
    dist = COEFFICIENTS[length]
    rng = np.random.default_rng(10 + length)
    uv = np.stack([rng.uniform(0.0, 639.0, 300), rng.uniform(0.0, 479.0, 300)], axis=1)
    xy = plumb_bob.undistorted(uv, K, plumb_bob.padded(dist))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    expected = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist, criteria=criteria)
    np.testing.assert_allclose(xy, expected.reshape(-1, 2), atol=1e-9)
    # and it is the projection's inverse
    back, _, _ = plumb_bob.project_with_jacobian(
        np.column_stack([xy, np.ones(len(xy))]), K, plumb_bob.padded(dist)
    )
    np.testing.assert_allclose(back, uv, atol=1e-8)


def test_behind_the_camera_is_flagged() -> None:
    dist = COEFFICIENTS[5]
    uv, _, in_front = plumb_bob.project_with_jacobian(
        np.array([[0.1, 0.0, -1.0], [0.0, 0.0, 1.0]]), K, plumb_bob.padded(dist)
    )
    assert in_front.tolist() == [False, True]
    assert np.isnan(uv[0]).all()


def test_a_camera_with_a_tilted_sensor_projects_and_normalises_as_opencv() -> None:
    tilted = COEFFICIENTS[14]
    camera = CameraModel(K, tilted, 640, 480)
    p = points(np.random.default_rng(3), 20)
    expected, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, tilted)
    uv = camera.project(p)[0]
    np.testing.assert_allclose(uv, expected.reshape(-1, 2), atol=1e-9)
    # the tilt moves the pixels: a test that could not pass without it
    untilted = CameraModel(K, tilted[:5], 640, 480)
    assert np.max(np.abs(untilted.project(p)[0] - uv)) > 1.0
    np.testing.assert_allclose(camera.normalize(uv), p[:, :2] / p[:, 2:], atol=1e-12)
