import math

import cv2
import numpy as np
import pytest

from perchpose.geometry import (
    angle_diff_rad,
    check_transform,
    facing_pose,
    invert_transform,
    lean_deg,
    rot_z,
    rotation_from_vector,
    rvec_tvec_from_transform,
    transform_from_rvec_tvec,
    vector_from_rotation,
    weighted_circular_mean_rad,
    wrap_angle_deg,
    wrap_angle_rad,
    yaw_rad,
)


@pytest.mark.parametrize(
    ("angle", "expected"),
    [(0.0, 0.0), (180.0, 180.0), (-180.0, 180.0), (190.0, -170.0), (-190.0, 170.0), (720.5, 0.5)],
)
def test_wrap_angle_deg_is_in_half_open_interval(angle: float, expected: float) -> None:
    assert wrap_angle_deg(angle) == pytest.approx(expected)


def test_wrap_angle_rad_never_returns_minus_pi() -> None:
    assert wrap_angle_rad(-math.pi) == math.pi
    assert wrap_angle_rad(3 * math.pi) == pytest.approx(math.pi)


def test_angle_difference_takes_the_short_way_round() -> None:
    assert math.degrees(angle_diff_rad(math.radians(-175), math.radians(175))) == pytest.approx(10)


def test_circular_mean_across_the_wrap() -> None:
    mean = weighted_circular_mean_rad(np.radians([175.0, -175.0]), np.array([0.5, 0.5]))
    assert abs(wrap_angle_deg(math.degrees(mean) - 180.0)) < 1e-9
    weighted = weighted_circular_mean_rad(np.radians([170.0, -170.0]), np.array([0.75, 0.25]))
    assert math.degrees(weighted) == pytest.approx(175.0, abs=0.1)


def test_inverse_and_composition_are_identities() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        T_a_b = facing_pose(*rng.uniform(-1, 1, 3), *rng.uniform(-3, 3, 3))
        T_b_c = facing_pose(*rng.uniform(-1, 1, 3), *rng.uniform(-3, 3, 3))
        T_a_c = T_a_b @ T_b_c
        np.testing.assert_allclose(invert_transform(T_a_b) @ T_a_c, T_b_c, atol=1e-12)
        np.testing.assert_allclose(T_a_b @ invert_transform(T_a_b), np.eye(4), atol=1e-12)


def test_rvec_round_trip() -> None:
    T = facing_pose(0.1, -0.2, 0.7, 2.0, 0.1, -0.2)
    rvec, tvec = rvec_tvec_from_transform(T)
    np.testing.assert_allclose(transform_from_rvec_tvec(rvec, tvec), T, atol=1e-12)


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0, 90.0, 175.0, -160.0, 180.0])
def test_facing_pose_yaw_is_the_estimate_yaw(yaw_deg: float) -> None:
    T = facing_pose(0.0, 0.0, 0.5, math.radians(yaw_deg))
    assert wrap_angle_deg(math.degrees(yaw_rad(T[:3, :3])) - yaw_deg) == pytest.approx(0, abs=1e-9)
    # the printed face looks back at the camera: target z points against the optical axis
    assert T[2, 2] == pytest.approx(-1.0)


def test_check_transform_names_the_argument() -> None:
    with pytest.raises(ValueError, match="T_bad must be a 4x4"):
        check_transform(np.eye(3), "T_bad")
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="orthonormal"):
        check_transform(bad)


def test_yaw_and_tilt_give_back_the_rotation() -> None:
    from perchpose.geometry import (
        facing_pose,
        rotation_from_angles,
        tilt_rad,
        yaw_rad,
    )

    for yaw, tx, ty in ((0.0, 0.0, 0.0), (2.9, 0.3, -0.2), (-3.1, -0.4, 0.35)):
        R = facing_pose(0.0, 0.0, 1.0, yaw, tx, ty)[:3, :3]
        roll, pitch = tilt_rad(R)
        assert np.allclose(rotation_from_angles(yaw_rad(R), roll, pitch), R, atol=1e-12)
    # facing the camera: no tilt, whatever the yaw
    assert tilt_rad(facing_pose(0.1, 0.0, 0.5, 2.0)[:3, :3]) == pytest.approx((0.0, 0.0))


def test_rotation_vector_jacobian_matches_small_turns() -> None:
    from perchpose.geometry import rotation_from_angles, rotation_vector_jacobian

    yaw, roll, pitch = 2.2, -0.3, 0.25
    R = rotation_from_angles(yaw, roll, pitch)
    J = rotation_vector_jacobian(yaw, pitch)
    step = 1e-6
    for k, (dr, dp, dy) in enumerate(np.eye(3) * step):
        turned = rotation_from_angles(yaw + dy, roll + dr, pitch + dp)
        small = turned @ R.T  # I + [w]x to first order
        w = np.array(
            [small[2, 1] - small[1, 2], small[0, 2] - small[2, 0], small[1, 0] - small[0, 1]]
        )
        assert np.allclose(w / (2 * step), J[:, k], atol=1e-5)


def test_the_rotation_vector_jacobian_inverse_is_its_inverse() -> None:
    from perchpose.geometry import rotation_vector_jacobian, rotation_vector_jacobian_inverse

    for yaw, pitch in ((0.3, -0.2), (-2.9, 1.2), (1.0, 0.0)):
        J = rotation_vector_jacobian(yaw, pitch)
        np.testing.assert_allclose(
            rotation_vector_jacobian_inverse(yaw, pitch) @ J, np.eye(3), atol=1e-12
        )


def test_a_rotation_vector_and_its_rotation_agree_with_opencv_and_invert() -> None:
    rng = np.random.default_rng(7)
    for w in [np.zeros(3), np.array([1e-9, 0.0, 0.0]), *rng.uniform(-1.5, 1.5, (20, 3))]:
        R = rotation_from_vector(w)
        expected, _ = cv2.Rodrigues(w.reshape(3, 1))
        np.testing.assert_allclose(R, expected, atol=1e-12)
        np.testing.assert_allclose(vector_from_rotation(R), w, atol=1e-9)
    np.testing.assert_allclose(rotation_from_vector([0.0, 0.0, 0.5]), rot_z(0.5), atol=1e-12)


def test_lean_is_the_angle_of_the_body_z_from_the_vertical_whatever_the_heading() -> None:
    R = rot_z(1.2) @ rotation_from_vector(np.array([0.0, np.radians(8.0), 0.0]))
    assert lean_deg(R) == pytest.approx(8.0)
    assert lean_deg(np.eye(3)) == 0.0
    assert lean_deg(np.diag([1.0, -1.0, -1.0])) == pytest.approx(180.0)
