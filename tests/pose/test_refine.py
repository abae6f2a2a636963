import cv2
import numpy as np

from perchpose.geometry import facing_pose, rot_x, transform_from_rvec_tvec
from perchpose.pose.refine import refine_pose

SQUARE_M = np.array([[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0]], np.float64) * 0.05


def _normalised(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    q = points @ T[:3, :3].T + T[:3, 3]
    return np.ascontiguousarray(q[:, :2] / q[:, 2:])


def _cost(R: np.ndarray, t: np.ndarray, points: np.ndarray, xy: np.ndarray) -> float:
    q = points @ R.T + t
    return float(np.sum((q[:, :2] / q[:, 2:] - xy) ** 2))


def test_exact_points_give_the_exact_pose_from_a_start_degrees_away() -> None:
    T = facing_pose(0.05, -0.02, 0.6, 1.1, 0.3, -0.2)
    xy = _normalised(T, SQUARE_M)
    start = rot_x(0.05) @ T[:3, :3]
    R, t, ok = refine_pose(SQUARE_M, xy, start, T[:3, 3] + [0.01, -0.01, 0.03])
    assert ok
    np.testing.assert_allclose(R, T[:3, :3], atol=1e-10)
    np.testing.assert_allclose(t, T[:3, 3], atol=1e-10)


def test_noisy_points_end_at_least_as_low_as_opencvs_refinement() -> None:
    rng = np.random.default_rng(3)
    for _ in range(40):
        T = facing_pose(*rng.uniform(-0.3, 0.3, 2), rng.uniform(0.2, 2.0), *rng.uniform(-1, 1, 3))
        xy = _normalised(T, SQUARE_M) + rng.normal(0.0, 1e-3, (4, 2))
        obj, img = SQUARE_M.reshape(4, 1, 3), xy.reshape(4, 1, 2)
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            obj, img, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        for rvec, tvec in zip(rvecs, tvecs, strict=True):
            start = transform_from_rvec_tvec(rvec, tvec)
            r_cv, t_cv = cv2.solvePnPRefineLM(obj, img, np.eye(3), None, rvec.copy(), tvec.copy())
            T_cv = transform_from_rvec_tvec(r_cv, t_cv)
            R, t, ok = refine_pose(SQUARE_M, xy, start[:3, :3].copy(), start[:3, 3].copy())
            assert ok
            ours, opencv = _cost(R, t, SQUARE_M, xy), _cost(T_cv[:3, :3], T_cv[:3, 3], SQUARE_M, xy)
            assert ours <= opencv * (1 + 1e-9) + 1e-18
            assert ours <= _cost(start[:3, :3], start[:3, 3], SQUARE_M, xy)
            np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)


def test_a_start_with_a_point_behind_the_camera_is_refused() -> None:
    T = facing_pose(0.0, 0.0, 0.5)
    xy = _normalised(T, SQUARE_M)
    _, t, ok = refine_pose(SQUARE_M, xy, T[:3, :3].copy(), np.array([0.0, 0.0, -0.5]))
    assert not ok
    np.testing.assert_array_equal(t, [0.0, 0.0, -0.5])
