"""Small compiled linear algebra against numpy's."""

import numpy as np
import pytest

from perchpose.numeric.linalg import (
    inverted,
    symmetric_eigenvalues,
    times,
    times_transposed,
    transposed_times,
)


@pytest.mark.parametrize("n", [3, 6, 16])
def test_products_inverse_and_eigenvalues(n: int) -> None:
    rng = np.random.default_rng(n)
    A, B = rng.normal(size=(n, n)), rng.normal(size=(n, 4))
    np.testing.assert_allclose(times(A, B), A @ B, atol=1e-12)
    np.testing.assert_allclose(transposed_times(A, B), A.T @ B, atol=1e-12)
    np.testing.assert_allclose(times_transposed(B.T, A), B.T @ A.T, atol=1e-12)
    solved, A_inv = inverted(A)
    assert solved
    np.testing.assert_allclose(A_inv, np.linalg.inv(A), rtol=1e-9, atol=1e-10)
    # symmetric, with eigenvalues spread over many orders of magnitude
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    values = np.logspace(-6, 8, n)
    sym = Q @ np.diag(values) @ Q.T
    sym = 0.5 * (sym + sym.T)
    found = symmetric_eigenvalues(sym)
    np.testing.assert_allclose(found, np.linalg.eigvalsh(sym), rtol=1e-6, atol=1e-7)
    assert np.all(np.diff(found) >= 0)


def test_a_singular_matrix_is_said() -> None:
    solved, _ = inverted(np.ones((4, 4)))
    assert not solved


def test_sandwiched_is_a_b_a_transposed() -> None:
    from perchpose.numeric.linalg import sandwiched

    rng = np.random.default_rng(4)
    A, B = rng.normal(size=(6, 6)), rng.normal(size=(6, 6))
    np.testing.assert_allclose(sandwiched(A, B), A @ B @ A.T, atol=1e-12)


def test_the_homography_of_four_points_maps_them_exactly() -> None:
    import cv2

    from perchpose.numeric.linalg import homography_of_4, through_homography

    src = np.array([[-0.05, 0.05], [0.05, 0.05], [0.05, -0.05], [-0.05, -0.05]])
    dst = np.array([[310.2, 200.7], [402.9, 208.1], [398.4, 297.3], [305.5, 290.0]])
    found, H = homography_of_4(src, dst)
    assert found
    assert H[2, 2] == 1.0
    np.testing.assert_allclose(through_homography(H, src), dst, atol=1e-9)
    inside = np.array([[0.0, 0.0], [0.02, -0.01]])
    expected = cv2.perspectiveTransform(inside.reshape(-1, 1, 2), H).reshape(-1, 2)
    np.testing.assert_allclose(through_homography(H, inside), expected, atol=1e-9)
    collinear = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    assert not homography_of_4(collinear, dst)[0]
