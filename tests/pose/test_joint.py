"""Joint PnP over all corners, its covariance, and the Cramer-Rao bound."""

import math

import cv2
import numpy as np
import pytest

from perchpose import CameraModel, TargetSpec
from perchpose.geometry import facing_pose
from perchpose.pose.joint import (
    pose_covariance,
    sandwich_covariance,
    solve_joint_pose,
    target_points,
    uncertainty,
)
from perchpose.pose.marker import solve_marker_pose
from perchpose.values import MarkerDetection


def noisy_detections(
    camera: CameraModel, target: TargetSpec, T: np.ndarray, sigma_px: float, rng
) -> tuple[MarkerDetection, ...]:
    out = []
    for i, m in enumerate(target.markers):
        uv, ok = camera.project((T[:3, :3] @ m.corners_target_m.T).T + T[:3, 3])
        assert np.all(ok)
        out.append(MarkerDetection(i, uv + rng.normal(0.0, sigma_px, uv.shape), "raw"))
    return tuple(out)


@pytest.mark.parametrize("camera_name", ["webcam", "fpv"])
def test_spread_of_the_joint_pose_matches_its_bound(camera_name: str) -> None:
    """Monte Carlo: with Gaussian corner noise the joint PnP's spread equals the Cramer-Rao
    bound (an efficient estimator), and the covariance it reports is that bound."""
    camera = CameraModel.preset(camera_name)
    target = TargetSpec.paper()
    T = facing_pose(0.03, -0.02, 0.3, 0.4, 0.1, -0.15)
    sigma = 0.1
    rng = np.random.default_rng(7)
    bound = pose_covariance(
        camera, T, target_points(target, noisy_detections(camera, target, T, 0.0, rng)), sigma
    )
    assert bound is not None
    expected = uncertainty(T, bound)
    samples = []
    for _ in range(300):
        dets = noisy_detections(camera, target, T, sigma, rng)
        first = solve_marker_pose(camera, target.markers[0], 0, dets[0].corners_px)
        assert first
        joint = solve_joint_pose(camera, target, dets, first.T_camera_target, sigma)
        assert joint is not None
        samples.append(
            [
                *joint.T_camera_target[:3, 3],
                math.atan2(joint.T_camera_target[1, 0], joint.T_camera_target[0, 0]),
            ]
        )
    spread = np.std(np.array(samples), axis=0)
    for got, want in zip(
        spread, (expected.x_m, expected.y_m, expected.z_m, expected.yaw_rad), strict=True
    ):
        assert got == pytest.approx(want, rel=0.15)
    # the reported covariance at the estimate is the bound's, to first order
    assert uncertainty(joint.T_camera_target, joint.covariance).z_m == pytest.approx(
        expected.z_m, rel=0.05
    )


def test_joint_pose_beats_the_outer_marker_alone() -> None:
    camera = CameraModel.preset("webcam")
    target = TargetSpec.paper()
    T = facing_pose(0.0, 0.01, 0.22, -0.3)
    rng = np.random.default_rng(8)
    errors_joint, errors_outer = [], []
    for _ in range(100):
        dets = noisy_detections(camera, target, T, 0.1, rng)
        outer = solve_marker_pose(camera, target.markers[0], 0, dets[0].corners_px)
        assert outer
        joint = solve_joint_pose(camera, target, dets, outer.T_camera_target, 0.1)
        assert joint is not None
        errors_outer.append(np.linalg.norm(outer.T_camera_target[:3, 3] - T[:3, 3]))
        errors_joint.append(np.linalg.norm(joint.T_camera_target[:3, 3] - T[:3, 3]))
    assert np.mean(errors_joint) < np.mean(errors_outer)


def test_bound_grows_with_distance() -> None:
    camera = CameraModel.preset("fpv")
    target = TargetSpec.paper()
    points = target.markers[0].corners_target_m
    near = pose_covariance(camera, facing_pose(0, 0, 0.5), points, 0.05)
    far = pose_covariance(camera, facing_pose(0, 0, 1.5), points, 0.05)
    assert near is not None
    assert far is not None
    # depth precision falls with the square of the distance
    ratio = (
        uncertainty(facing_pose(0, 0, 1.5), far).z_m / uncertainty(facing_pose(0, 0, 0.5), near).z_m
    )
    assert 6.0 < ratio < 12.0


def test_sandwich_covariance_of_correlated_corners() -> None:
    """With the weights' own independent noise it is the plain covariance; with corner errors
    that are correlated (the outer marker's corners all shifted together by one draw, plus a
    little of their own) it matches the spread of the poses that ``solve_joint_pose``
    actually fits to 400 such draws."""
    camera = CameraModel.preset("fpv")
    target = TargetSpec.paper()
    T = facing_pose(0.02, -0.01, 0.6, 0.3)
    points = target.markers[0].corners_target_m
    plain = pose_covariance(camera, T, points, 0.05)
    same = sandwich_covariance(camera, T, points, 0.05, 0.05**2 * np.eye(8))
    assert plain is not None
    assert same is not None
    assert np.allclose(same, plain, rtol=1e-9, atol=0.0)
    S = 0.05**2 * (np.kron(np.ones((4, 4)), np.eye(2)) + 0.2 * np.eye(8))
    together = sandwich_covariance(camera, T, points, 0.05, S)
    assert together is not None
    uv, _ = camera.project(points @ T[:3, :3].T + T[:3, 3])
    rng = np.random.default_rng(0)
    draws = rng.multivariate_normal(np.zeros(8), S, 400)
    positions = []
    for draw in draws:
        detection = MarkerDetection(0, uv + draw.reshape(4, 2), "raw")
        joint = solve_joint_pose(camera, target, (detection,), T, 0.05)
        assert joint is not None
        positions.append(joint.T_camera_target[:3, 3])
    spread = np.std(positions, axis=0)
    predicted = uncertainty(T, together)
    assert spread[0] == pytest.approx(predicted.x_m, rel=0.1)
    assert spread[1] == pytest.approx(predicted.y_m, rel=0.1)
    assert spread[2] == pytest.approx(predicted.z_m, rel=0.1)
    # and not what independent corners of the same size would give
    assert abs(uncertainty(T, plain).x_m / predicted.x_m - 1.0) > 0.2


def test_corner_misfit_is_the_variance_factor() -> None:
    """Corner errors drawn from the covariance the fit is told: the residuals' squared length
    in its metric averages its expected value (factor 1); errors twice as large give 4."""
    from perchpose.pose.joint import corner_misfit

    camera = CameraModel.preset("fpv")
    target = TargetSpec.paper()
    T = facing_pose(0.02, -0.01, 0.6, 0.3)
    points = target.markers[0].corners_target_m
    uv, _ = camera.project(points @ T[:3, :3].T + T[:3, 3])
    S = 0.05**2 * (np.eye(8) - 0.5 * np.kron(np.eye(4), np.ones((2, 2))) + 0.5 * np.eye(8))
    rng = np.random.default_rng(1)
    for scale, factor in ((1.0, 1.0), (2.0, 4.0)):
        observed = expected = 0.0
        for draw in rng.multivariate_normal(np.zeros(8), scale**2 * S, 300):
            detection = MarkerDetection(0, uv + draw.reshape(4, 2), "raw")
            joint = solve_joint_pose(camera, target, (detection,), T, 0.05, corner_covariance_px2=S)
            assert joint is not None
            observed += joint.misfit[0]
            expected += joint.misfit[1]
        assert observed / expected == pytest.approx(factor, rel=0.15)
    # the statistic itself, on residuals of a known size
    J = np.zeros((8, 6))
    J[:6, :6] = np.eye(6)
    assert corner_misfit(J, np.ones(8), np.zeros(8), np.eye(8)) == (0.0, pytest.approx(2.0))


@pytest.mark.parametrize("camera_name", ["webcam", "fpv"])
def test_the_pose_jacobian_is_what_small_moves_of_the_pose_do(camera_name: str) -> None:
    """Columns of the pixels' Jacobian over (w, dt), by central differences of
    ``R' = exp([w]x) R``, ``t' = t + dt`` through the camera's own projection."""
    from perchpose.pose.joint import _project_with_jacobian

    camera = CameraModel.preset(camera_name)
    target = TargetSpec.paper()
    T = facing_pose(0.05, -0.04, 0.35, 0.7, 0.3, -0.2)
    points = target_points(
        target, noisy_detections(camera, target, T, 0.0, np.random.default_rng(0))
    )
    projected = _project_with_jacobian(camera, T[:3, :3], T[:3, 3], points)
    assert projected is not None
    step = 1e-7
    expected = np.zeros((2 * len(points), 6))
    for k in range(6):
        columns = []
        for sign in (1.0, -1.0):
            delta = np.zeros(6)
            delta[k] = sign * step
            R, _ = cv2.Rodrigues(delta[:3].reshape(3, 1))
            moved = (np.asarray(R) @ T[:3, :3] @ points.T).T + T[:3, 3] + delta[3:]
            columns.append(camera.project(moved)[0].reshape(-1))
        expected[:, k] = (columns[0] - columns[1]) / (2 * step)
    np.testing.assert_allclose(projected[1], expected, rtol=1e-5, atol=1e-3)


def test_the_measurement_jacobian_is_what_small_turns_do_to_the_yaw() -> None:
    from perchpose.geometry import yaw_rad
    from perchpose.pose.joint import measurement_jacobian

    T = facing_pose(0.05, -0.04, 0.35, 2.9, 0.4, -0.3)
    step = 1e-7
    expected = np.zeros(3)
    for k in range(3):
        delta = np.zeros(3)
        delta[k] = step
        R_plus, _ = cv2.Rodrigues(delta.reshape(3, 1))
        R_minus, _ = cv2.Rodrigues(-delta.reshape(3, 1))
        plus = yaw_rad(np.asarray(R_plus) @ T[:3, :3])
        minus = yaw_rad(np.asarray(R_minus) @ T[:3, :3])
        expected[k] = math.remainder(plus - minus, 2 * math.pi) / (2 * step)
    J = measurement_jacobian(T)
    np.testing.assert_allclose(J[0, :3], expected, atol=1e-7)
    np.testing.assert_array_equal(J[1:, 3:], np.eye(3))
    assert not J[0, 3:].any()
    assert not J[1:, :3].any()


def test_compiled_covariances_and_misfit_are_the_matrix_formulas() -> None:
    from perchpose.pose.joint import _covariances, corner_misfit

    rng = np.random.default_rng(11)
    J = rng.normal(size=(16, 6)) * np.array([200.0, 200.0, 50.0, 900.0, 900.0, 300.0])
    w = rng.uniform(20.0, 100.0, 16)
    A = rng.normal(size=(16, 16))
    S = 0.01 * (A @ A.T + 16 * np.eye(16))
    r = rng.normal(0.0, 0.1, 16)
    Jw = J * w[:, None]
    H_inv = np.linalg.inv(J.T @ Jw)
    plain, own = _covariances(J, w, S)
    assert plain is not None
    assert own is not None
    np.testing.assert_allclose(plain, H_inv, rtol=1e-9)
    B = Jw @ H_inv
    np.testing.assert_allclose(own, B.T @ S @ B, rtol=1e-9)
    assert _covariances(J, w)[1] is None
    M = np.eye(16) - J @ H_inv @ Jw.T
    S_inv = np.linalg.inv(S)
    observed, expected = corner_misfit(J, w, r, S)
    assert observed == pytest.approx(float(r @ S_inv @ r), rel=1e-9)
    assert expected == pytest.approx(float(np.trace(S_inv @ M @ S @ M.T)), rel=1e-9)
    # a Jacobian that leaves a direction unseen has no covariance
    flat = J.copy()
    flat[:, 5] = 0.0
    assert _covariances(flat, w, S) == (None, None)
    assert all(np.isnan(corner_misfit(J, w, r, np.zeros((16, 16)))))
