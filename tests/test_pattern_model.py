"""The compiled printed-pattern model (``perchpose.pattern_model``)."""

import numpy as np

from perchpose.pattern_fit import printed_pattern
from perchpose.pattern_model import normal_equations
from perchpose.target import TargetSpec


def _basis(code: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.stack([code != -1, code == 1, code == -1]), np.float64)


def test_merged_bands_model_the_whole_grid(paper_target: TargetSpec) -> None:
    """Neighbouring bands printed alike are merged per pixel (the CDFs at the fine lines of
    the inner marker are not evaluated where no row within reach changes there): the normal
    equations are those of the unmerged grid. Unmerged: a print whose every cell differs from
    its neighbours by 1e-9, so that nothing merges."""
    pattern = printed_pattern(paper_target, 0)
    assert pattern is not None
    rng = np.random.default_rng(3)
    # points over the whole marker (the inner one's fine cells at u, v in 2.5-3.5) and its
    # margin, through a mild homography
    q = np.ascontiguousarray(rng.uniform(-0.05, 1.05, (600, 2)))
    g = np.array([5.9, 0.2, 0.1, -0.15, 6.1, -0.05, 0.03, -0.02])
    blur_q = np.array([[0.045, 0.004], [-0.003, 0.05]])
    values = rng.uniform(40, 200, len(q))
    levels = np.array([60.0, 120.0, 80.0])
    basis = _basis(pattern.code)
    unmerged = basis + 1e-9 * rng.uniform(size=basis.shape)
    lines_u, lines_v = pattern.lines_u, pattern.lines_v
    JtJ, Jtr, cover = normal_equations(q, values, g, blur_q, lines_u, lines_v, basis, levels)
    JtJ_all, Jtr_all, cover_all = normal_equations(
        q, values, g, blur_q, lines_u, lines_v, unmerged, levels
    )
    assert np.allclose(JtJ, JtJ_all, rtol=1e-6, atol=1e-6 * np.abs(JtJ_all).max())
    assert np.allclose(Jtr, Jtr_all, rtol=1e-6, atol=1e-6 * np.abs(Jtr_all).max())
    assert np.allclose(cover, cover_all, atol=1e-6)
