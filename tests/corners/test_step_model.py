"""The compiled blurred-step model and its Gauss-Newton fit, on profiles made from the model."""

import math

import numpy as np
import pytest

from perchpose.corners.step_model import fit_steps, pixel_step
from perchpose.numeric.normal import normal_cdf_pdf_at


def test_normal_cdf_and_density() -> None:
    for u in (-3.0, -0.7, 0.0, 0.4, 2.5):
        cdf, pdf = normal_cdf_pdf_at(u)
        assert cdf == pytest.approx(0.5 * math.erfc(-u / math.sqrt(2.0)), abs=2e-7)
        assert pdf == pytest.approx(math.exp(-0.5 * u * u) / math.sqrt(2.0 * math.pi), rel=1e-12)


def test_pixel_step_derivatives_match_finite_differences() -> None:
    t, sigma, h = 0.3, 0.8, 1e-6
    value, d_t, d_log_sigma = pixel_step(t, sigma)
    assert 0.0 < value < 1.0
    # the CDF's approximation (to 1.5e-7) is not exactly the density's integral: the analytic
    # slope and the slope of the approximated values differ by about 1e-6
    assert d_t == pytest.approx(
        (pixel_step(t + h, sigma)[0] - pixel_step(t - h, sigma)[0]) / (2 * h), abs=2e-6
    )
    up, down = pixel_step(t, sigma * math.exp(h))[0], pixel_step(t, sigma * math.exp(-h))[0]
    assert d_log_sigma == pytest.approx((up - down) / (2 * h), abs=2e-6)


def profiles(
    rng: np.random.Generator, d_true: np.ndarray, sigma: float, white: np.ndarray, border_px: float
) -> np.ndarray:
    """(3, K, M): pixel offsets across the edge, their grey values (dark 40, light 190) and
    weights (1)."""
    K = len(d_true)
    at = np.arange(-3.0, 4.0, 0.35)[None, :] + rng.uniform(-0.1, 0.1, (K, 1))
    values = np.empty_like(at)
    for k in range(K):
        for m in range(at.shape[1]):
            t = at[k, m] - d_true[k]
            step = pixel_step(t, sigma)[0] + white[k] * (1.0 - pixel_step(t + border_px, sigma)[0])
            values[k, m] = 40.0 + 150.0 * step
    return np.stack([at, values, np.ones_like(at)])


@pytest.mark.parametrize("with_white", [False, True])
def test_the_fit_recovers_edges_and_blur(with_white: bool) -> None:
    rng = np.random.default_rng(3)
    K, sigma, border_px = 16, 0.9, 2.5
    d_true = rng.uniform(-0.4, 0.4, K)
    white = (rng.uniform(size=K) < 0.5).astype(float) if with_white else np.zeros(K)
    pixels = profiles(rng, d_true, sigma, white, border_px)
    d = np.zeros(K)
    levels = np.array([[60.0], [110.0]])
    surround = np.stack([white, np.full(K, border_px), np.full(K, 1e6)])
    W = np.ones((1, K))
    ok, log_sigma = fit_steps(pixels, d, W, levels, math.log(1.5), surround, False, 12)
    assert ok
    np.testing.assert_allclose(d, d_true, atol=1e-5)
    assert math.exp(log_sigma) == pytest.approx(sigma, abs=1e-5)
    np.testing.assert_allclose(levels[:, 0], [40.0, 150.0], atol=1e-3)


def test_an_edge_from_light_to_dark_is_refused() -> None:
    rng = np.random.default_rng(4)
    K = 8
    pixels = profiles(rng, np.zeros(K), 0.8, np.zeros(K), 2.0)
    pixels[1] = 230.0 - pixels[1]  # light inside, dark outside: not a marker's border
    surround = np.stack([np.zeros(K), np.zeros(K), np.full(K, 1e6)])
    levels = np.array([[60.0], [110.0]])
    ok, _ = fit_steps(pixels, np.zeros(K), np.ones((1, K)), levels, 0.0, surround, False, 8)
    assert not ok


def test_a_pixel_weighted_by_its_count_fits_as_its_repeats_do() -> None:
    # profiles whose pixels repeat (as where samples are closer than a pixel), against the
    # same pixels once each with their counts for weights, and noise so the fit is not exact
    rng = np.random.default_rng(5)
    K, sigma = 12, 1.1
    once = profiles(rng, rng.uniform(-0.4, 0.4, K), sigma, np.zeros(K), 2.5)
    once[1] += rng.normal(0.0, 3.0, once[1].shape)
    counts = rng.integers(1, 4, once.shape[1:])
    M = int(counts.sum(axis=1).max())
    repeated = np.zeros((3, K, M))
    weighted = np.zeros((3, K, M))
    for k in range(K):
        at = np.repeat(once[0, k], counts[k])
        repeated[:2, k, : len(at)] = at, np.repeat(once[1, k], counts[k])
        repeated[2, k, : len(at)] = 1.0
        first = np.concatenate([[0], np.cumsum(counts[k])[:-1]])
        weighted[:2, k, : len(at)] = repeated[:2, k, : len(at)]
        weighted[2, k, first] = counts[k]
    surround = np.stack([np.zeros(K), np.full(K, 2.5), np.full(K, 1e6)])
    results = []
    for pixels in (repeated, weighted):
        d, levels = np.zeros(K), np.array([[60.0], [110.0]])
        ok, log_sigma = fit_steps(pixels, d, np.ones((1, K)), levels, 0.0, surround, False, 8)
        assert ok
        results.append((d, log_sigma, levels))
    np.testing.assert_allclose(results[1][0], results[0][0], atol=1e-9)
    assert results[1][1] == pytest.approx(results[0][1], abs=1e-9)
    np.testing.assert_allclose(results[1][2], results[0][2], atol=1e-7)
    # and a pixel of weight 0 is left out whatever its value
    spoilt = weighted.copy()
    spoilt[1][spoilt[2] == 0] = 255.0
    d, levels = np.zeros(K), np.array([[60.0], [110.0]])
    fit_steps(spoilt, d, np.ones((1, K)), levels, 0.0, surround, False, 8)
    np.testing.assert_allclose(d, results[1][0], atol=1e-9)
