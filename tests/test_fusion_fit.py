"""The sigma fits of perchpose.fusion (closed-form least squares and the paper's LMS)."""

import math

import numpy as np
import pytest

from perchpose.fusion import fit_sigma_least_squares, fit_sigma_lms


@pytest.mark.parametrize("true_sigma", [0.275, 0.5, 0.728, 0.9])
def test_both_fits_recover_a_known_sigma(true_sigma: float) -> None:
    # inner and outer share an error e; the outer has -(1 - s)/s of it... built so that
    # s * outer + (1 - s) * inner equals the truth plus small noise exactly when s = true_sigma
    rng = np.random.default_rng(1)
    truth = rng.uniform(-20, 20, 2000)
    common = rng.normal(0, 1.0, 2000)
    outer = truth + (1 - true_sigma) * common
    inner = truth - true_sigma * common
    noise = rng.normal(0, 0.01, 2000)
    ls = fit_sigma_least_squares(outer + noise, inner, truth)
    lms, passes = fit_sigma_lms(outer + noise, inner, truth)
    assert ls == pytest.approx(true_sigma, abs=0.01)
    assert lms == pytest.approx(ls, abs=0.01)
    assert passes < 200


def test_least_squares_is_the_variance_weighting_for_independent_errors() -> None:
    rng = np.random.default_rng(2)
    truth = rng.uniform(-5, 5, 20000)
    outer = truth + rng.normal(0, 0.3, truth.size)
    inner = truth + rng.normal(0, 0.6, truth.size)
    expected = 0.6**2 / (0.3**2 + 0.6**2)  # the inverse-variance weight of the outer marker
    assert fit_sigma_least_squares(outer, inner, truth) == pytest.approx(expected, abs=0.01)


def test_yaw_fit_works_across_the_wrap() -> None:
    rng = np.random.default_rng(3)
    truth = np.radians(rng.choice([179.0, -179.0, 178.5], 3000))
    outer = truth + np.radians(rng.normal(0, 0.5, truth.size))
    inner = truth + np.radians(rng.normal(0, 0.5, truth.size))
    wrap = lambda a: np.remainder(a + math.pi, 2 * math.pi) - math.pi  # noqa: E731
    ls = fit_sigma_least_squares(wrap(outer), wrap(inner), truth, circular=True)
    lms, _ = fit_sigma_lms(wrap(outer), wrap(inner), truth, circular=True)
    assert ls == pytest.approx(0.5, abs=0.03)
    assert lms == pytest.approx(ls, abs=0.01)


def test_identical_markers_cannot_be_fitted() -> None:
    x = np.linspace(0, 1, 10)
    with pytest.raises(ValueError, match="not determined"):
        fit_sigma_least_squares(x, x, x + 1)
    with pytest.raises(ValueError, match="not determined"):
        fit_sigma_lms(x, x, x + 1)


def test_both_fits_hold_sigma_to_a_weighted_mean() -> None:
    """Errors of the same sign, the inner marker's three times the outer's: the unconstrained
    optimum is sigma = 1.5, which would extrapolate past the outer marker; the paper's fusion
    takes weights in [0, 1], and both fits give the constrained optimum, 1."""
    rng = np.random.default_rng(4)
    truth = rng.uniform(-20, 20, 500)
    error = rng.normal(0, 1.0, 500)
    outer, inner = truth + error, truth + 3.0 * error
    assert fit_sigma_least_squares(outer, inner, truth) == 1.0
    lms, _ = fit_sigma_lms(outer, inner, truth)
    assert lms == 1.0
    # and the other side: the outer marker the worse one by far
    assert fit_sigma_least_squares(inner, outer, truth) == 0.0
