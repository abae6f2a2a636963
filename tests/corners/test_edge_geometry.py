import math

import numpy as np
import pytest

from perchpose.corners.edge_geometry import (
    bilinear_points,
    corner_covariance,
    corner_probes,
    edge_points_n,
    fit_lines,
    intersect_sides,
    largest_move,
    lens_jacobians,
    outward_normals,
    sample_profiles,
    side_lengths,
    side_probes,
)

SQUARE = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])


def _square_lines() -> tuple[np.ndarray, np.ndarray]:
    """The sides of SQUARE as n . x = c, in ArUco order (top, right, bottom, left)."""
    normals = np.array([[0.0, 1.0], [1.0, 0.0], [0.0, 1.0], [1.0, 0.0]])
    return normals, np.array([0.0, 2.0, 2.0, 0.0])


def test_fit_lines_recovers_noisy_lines_and_trims_an_outlier() -> None:
    rng = np.random.default_rng(3)
    along = np.linspace(-1.0, 1.0, 40)
    angles = np.array([0.3, -1.2])
    points = np.empty((2, 40, 2))
    for s, a in enumerate(angles):
        direction = np.array([math.cos(a), math.sin(a)])
        normal = np.array([-direction[1], direction[0]])
        points[s] = 0.5 * s + along[:, None] * direction + rng.normal(0, 1e-3, (40, 1)) * normal
    points[0, 7] += 0.2 * np.array([-math.sin(0.3), math.cos(0.3)])  # far off its line
    ok, normals, offsets, centres, angle_var, shift_var = fit_lines(points, np.ones((2, 40), bool))
    assert ok
    for s, a in enumerate(angles):
        turn = math.atan2(normals[s, 1], normals[s, 0]) - (a + math.pi / 2)
        assert abs(math.remainder(turn, math.pi)) < 1e-3
        assert abs(normals[s] @ centres[s] - offsets[s]) < 1e-12
    # the outlier left out: the scatter is the noise's, 1e-3 px
    assert 0.5e-3 < math.sqrt(shift_var[0] * 39) < 1.5e-3
    assert np.all(angle_var > 0)


def test_fit_lines_refuses_a_set_under_three_points() -> None:
    points = np.zeros((1, 5, 2))
    points[0, :, 0] = np.arange(5.0)
    usable = np.array([[True, True, False, False, False]])
    assert not fit_lines(points, usable)[0]


def test_intersect_sides_finds_the_square_and_refuses_parallel_sides() -> None:
    normals, offsets = _square_lines()
    met, corners, A_inv = intersect_sides(normals, offsets)
    assert met
    np.testing.assert_allclose(corners, SQUARE, atol=1e-12)
    for i in range(4):
        A = np.stack([normals[(i + 3) % 4], normals[i]])
        np.testing.assert_allclose(A_inv[i] @ A, np.eye(2), atol=1e-12)
    normals[1] = normals[0]
    assert not intersect_sides(normals, offsets)[0]


def test_corner_covariance_moves_corners_as_the_lines_move() -> None:
    normals, offsets = _square_lines()
    centres = np.array([[1.0, 0.0], [2.0, 1.0], [1.0, 2.0], [0.0, 1.0]])
    _, corners, A_inv = intersect_sides(normals, offsets)
    lens = np.tile(3.0 * np.eye(2), (4, 1, 1))  # 3 px per unit
    for side in range(4):
        for which in ("angle", "shift"):
            angle_var, shift_var = np.zeros(4), np.zeros(4)
            (angle_var if which == "angle" else shift_var)[side] = 1.0
            cov = corner_covariance(lens, A_inv, corners, normals, centres, angle_var, shift_var)
            # move the line by a small amount of that kind and intersect again
            h = 1e-6
            n, c = normals.copy(), offsets.copy()
            if which == "angle":
                turn = np.array([[math.cos(h), -math.sin(h)], [math.sin(h), math.cos(h)]])
                n[side] = turn @ normals[side]
                c[side] = n[side] @ centres[side]
            else:
                c[side] += h
            moved = (intersect_sides(n, c)[1] - corners).reshape(8) * 3.0 / h
            np.testing.assert_allclose(cov, np.outer(moved, moved), atol=1e-5)


def test_side_probes_and_outward_normals_of_a_square() -> None:
    t = np.array([0.25, 0.5, 0.75])
    p_n, step_n, perp_n, probes = side_probes(SQUARE, t)
    assert probes.shape == (36, 3)
    assert np.all(probes[:, 2] == 1.0)
    np.testing.assert_allclose(p_n[1], [1.0, 0.0])  # the top side's middle
    np.testing.assert_allclose(p_n[4], [2.0, 1.0])  # the right side's middle
    np.testing.assert_allclose(probes[12:24, :2], p_n + step_n)
    np.testing.assert_allclose(probes[24:, :2], p_n + perp_n)
    normal = outward_normals(probes[:, :2] * 10.0, 10.0, 10.0)  # a pinhole of 10 px a unit
    np.testing.assert_allclose(normal[1], [0.0, -1.0], atol=1e-12)  # the top side faces up
    np.testing.assert_allclose(normal[4], [1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(normal[7], [0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(normal[10], [-1.0, 0.0], atol=1e-12)


def test_edge_points_follow_the_normal_through_the_lens_jacobian() -> None:
    t = np.array([0.5])
    p_n, step_n, perp_n, probes = side_probes(SQUARE, t)
    projected = probes[:, :2] * np.array([10.0, 20.0])  # unequal pixels per unit on x and y
    normal = outward_normals(projected, 10.0, 20.0)
    d_px = np.array([2.0, 3.0, np.nan, -1.0])
    edge = edge_points_n(p_n, step_n, perp_n, projected, normal, d_px)
    expected = p_n + np.nan_to_num(d_px)[:, None] * normal / np.array([10.0, 20.0])
    np.testing.assert_allclose(edge, expected, atol=1e-12)


def test_sample_profiles_bilinear_and_nearest_pixels() -> None:
    ys, xs = np.mgrid[0:20, 0:30]
    grey = (3 * xs + 2 * ys).astype(np.uint8)  # a plane: bilinear is exact on it
    p_px = np.array([[10.3, 7.6], [28.5, 10.0]])
    normal = np.array([[0.6, 0.8], [1.0, 0.0]])
    offsets = np.array([-1.5, -0.5, 0.5, 1.5])
    values, (at, data, counts), whole = sample_profiles(grey, p_px, normal, offsets)
    points = p_px[:, None, :] + offsets[None, :, None] * normal[:, None, :]
    np.testing.assert_allclose(values[0], 3 * points[0, :, 0] + 2 * points[0, :, 1])
    nearest = np.round(points[0])
    np.testing.assert_allclose(at[0], (nearest - p_px[0]) @ normal[0])
    np.testing.assert_array_equal(data[0], 3 * nearest[:, 0] + 2 * nearest[:, 1])
    # the second profile runs off the right edge of the image: NaN there, not whole
    assert whole[0]
    assert not whole[1]
    assert np.isnan(values[1, 2])
    assert np.isfinite(values[1, 0])
    np.testing.assert_allclose(bilinear_points(grey, points[0]), values[0])
    # halves round to the even pixel, as numpy's
    start, across = np.array([[2.0, 3.0]]), np.array([[1.0, 0.0]])
    _, half, _ = sample_profiles(grey, start, across, offsets)  # x 0.5, 1.5, 2.5, 3.5
    np.testing.assert_allclose(half[0, 0], np.array([0.0, 2.0, 2.0, 4.0]) - 2.0)
    # a pixel two samples share counts twice at the first of them, 0 at the other
    np.testing.assert_array_equal(half[2, 0], [1.0, 2.0, 0.0, 1.0])
    np.testing.assert_array_equal(counts[0], np.ones(4))  # 1 px apart: each its own pixel


def test_sample_profiles_count_every_sample_once() -> None:
    grey = np.zeros((40, 40), np.uint8)
    rng = np.random.default_rng(2)
    angles = rng.uniform(0.0, 2.0 * np.pi, 50)
    p_px = rng.uniform(12.0, 28.0, (50, 2))
    normal = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    offsets = np.arange(-4.0, 5.0, 0.35)
    _, pixels, _ = sample_profiles(grey, p_px, normal, offsets)
    np.testing.assert_array_equal(pixels[2].sum(axis=1), len(offsets))
    # each counted pixel is a different one from the last counted before it
    points = p_px[:, None, :] + offsets[None, :, None] * normal[:, None, :]
    nearest = np.round(points)
    for k in range(50):
        counted = nearest[k][pixels[2, k] > 0]
        assert np.all(np.any(np.diff(counted, axis=0) != 0, axis=1))
        assert len(np.unique(counted, axis=0)) == len(counted)


def test_side_lengths_and_largest_move() -> None:
    quad = np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 10.0], [-1.0, 10.0]])
    np.testing.assert_allclose(side_lengths(quad), [5.0, 6.0, 4.0, np.hypot(1.0, 10.0)])
    moved = quad + np.array([[0.0, 0.0], [0.3, 0.4], [0.0, -1.0], [0.0, 0.0]])
    assert largest_move(moved, quad) == pytest.approx(1.0)
    assert largest_move(quad, quad) == 0.0


def test_corner_probes_give_the_lens_jacobian() -> None:
    corners_n = np.array([[0.1, -0.2], [0.3, -0.1], [0.25, 0.2], [0.05, 0.1]])
    probes = corner_probes(corners_n, 1e-6)
    assert probes.shape == (12, 3)
    np.testing.assert_array_equal(probes[:, 2], 1.0)
    np.testing.assert_array_equal(probes[:4, :2], corners_n)
    # an affine lens: pixels = A xy + c, whose Jacobian is A everywhere
    A = np.array([[400.0, 3.0], [0.0, 390.0]])
    projected = probes[:, :2] @ A.T + np.array([320.0, 240.0])
    corners_px, lens = lens_jacobians(projected, 1e-6)
    np.testing.assert_allclose(corners_px, corners_n @ A.T + np.array([320.0, 240.0]))
    for i in range(4):
        np.testing.assert_allclose(lens[i], A, rtol=1e-6, atol=1e-3)
