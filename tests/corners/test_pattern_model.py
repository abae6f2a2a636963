"""The compiled printed-pattern model (``perchpose.corners.pattern_model``)."""

import numpy as np

from perchpose.corners.pattern_fit import printed_pattern
from perchpose.corners.pattern_model import banded, normal_equations
from perchpose.target import TargetSpec


def _basis(code: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.stack([code != -1, code == 1, code == -1]), np.float64)


def _mild_view(rng: np.random.Generator, points: int) -> tuple[np.ndarray, ...]:
    """Marker-plane points over the whole outer marker (the inner one's fine cells at u, v
    in 2.5-3.5) and its margin, a mild homography from them to cells, a blur, grey levels."""
    q = np.ascontiguousarray(rng.uniform(-0.05, 1.05, (points, 2)))
    g = np.array([5.9, 0.2, 0.1, -0.15, 6.1, -0.05, 0.03, -0.02])
    blur_q = np.array([[0.045, 0.004], [-0.003, 0.05]])
    return q, g, blur_q, np.array([60.0, 120.0, 80.0])


def test_merged_bands_model_the_whole_grid(paper_target: TargetSpec) -> None:
    """Neighbouring bands printed alike are merged per pixel (the CDFs at the fine lines of
    the inner marker are not evaluated where no row within reach changes there): the normal
    equations are those of the unmerged grid. Unmerged: a print whose every cell differs from
    its neighbours by 1e-9, so that nothing merges."""
    pattern = printed_pattern(paper_target, 0)
    assert pattern is not None
    rng = np.random.default_rng(3)
    q, g, blur_q, levels = _mild_view(rng, 600)
    values = rng.uniform(40, 200, len(q))
    basis = _basis(pattern.code)
    unmerged = basis + 1e-9 * rng.uniform(size=basis.shape)
    lines_u, lines_v = pattern.lines_u, pattern.lines_v
    no_rows = (np.zeros((0, 2), np.int64), 0, False)
    JtJ, Jtr, cover, _ = normal_equations(
        q, values, g, blur_q, (lines_u, lines_v, basis), levels, no_rows
    )
    JtJ_all, Jtr_all, cover_all, _ = normal_equations(
        q, values, g, blur_q, (lines_u, lines_v, unmerged), levels, no_rows
    )
    assert np.allclose(JtJ, JtJ_all, rtol=1e-6, atol=1e-6 * np.abs(JtJ_all).max())
    assert np.allclose(Jtr, Jtr_all, rtol=1e-6, atol=1e-6 * np.abs(Jtr_all).max())
    assert np.allclose(cover, cover_all, atol=1e-6)


def test_bands_over_the_rows_are_eliminated_and_detected(paper_target: TargetSpec) -> None:
    """With the cosines over the rows eliminated, a grey that follows them (bands of analog
    interference) changes nothing in the equations; without, it does. The score test over
    the rows stays near 1 for residuals independent of the row and grows with such bands;
    the same grey along the columns (shading, not interference) is told apart."""
    pattern = printed_pattern(paper_target, 0)
    assert pattern is not None
    rng = np.random.default_rng(5)
    q, g, blur_q, levels = _mild_view(rng, 2000)
    grid = (pattern.lines_u, pattern.lines_v, _basis(pattern.code))
    n_lines, K = 40, 4
    pixel_of = rng.integers(0, n_lines, (len(q), 2))
    values = rng.normal(100.0, 5.0, len(q))
    k = np.arange(1, K + 1)
    amplitudes = np.array([20.0, -15.0, 10.0, 18.0])

    def cosines(line: np.ndarray) -> np.ndarray:
        return np.cos(np.pi * k[None, :] * (line[:, None] + 0.5) / n_lines) @ amplitudes

    greys = {
        "plain": values,
        "rows": values + cosines(pixel_of[:, 0]),
        "columns": values + cosines(pixel_of[:, 1]),
    }
    results = {
        (name, eliminate): normal_equations(q, v, g, blur_q, grid, levels, (pixel_of, K, eliminate))
        for name, v in greys.items()
        for eliminate in (False, True)
    }
    JtJ, Jtr, _, plain = results["plain", True]
    JtJ_b, Jtr_b, _, rows = results["rows", True]
    assert np.allclose(JtJ, JtJ_b)
    assert np.allclose(Jtr, Jtr_b, atol=1e-9 * np.abs(Jtr).max())
    _, Jtr_kept, _, _ = results["plain", False]
    _, Jtr_kept_b, _, _ = results["rows", False]
    assert np.abs(Jtr_kept_b - Jtr_kept).max() > 0.01 * np.abs(Jtr_kept).max()
    assert 0.3 < plain[0] < 3.0
    assert 0.3 < plain[1] < 3.0
    assert rows[0] > 20.0
    assert results["plain", False][3] == plain
    assert banded(rows, 4.0)
    assert not banded(plain, 4.0)
    assert not banded(results["columns", True][3], 4.0)
