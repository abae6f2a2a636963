"""Fitting the paper fusion's weights offline: for one pose component, the sigma that best
blends the outer and inner markers' estimates into the truth, in closed form
(``fit_sigma_least_squares``) or by the paper's iterative LMS (``fit_sigma_lms``)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def _residual_pair(outer: Array, inner: Array, truth: Array, circular: bool) -> tuple[Array, Array]:
    """d = outer - inner and r = truth - inner (wrapped to (-pi, pi] when ``circular``)."""
    d = np.asarray(outer, np.float64) - np.asarray(inner, np.float64)
    r = np.asarray(truth, np.float64) - np.asarray(inner, np.float64)
    if circular:
        d = np.remainder(d + np.pi, 2 * np.pi) - np.pi
        r = np.remainder(r + np.pi, 2 * np.pi) - np.pi
    return d, r


def fit_sigma_least_squares(
    outer: Array, inner: Array, truth: Array, circular: bool = False
) -> float:
    """Closed-form sigma in [0, 1] minimising the mean of
    (sigma*outer + (1-sigma)*inner - truth)^2.

    outer, inner, truth : (N,) one component, same unit (radians if ``circular``).
    Writing the fused value as inner + sigma * (outer - inner), the unconstrained minimiser is
    sum(d * r) / sum(d * d) with d = outer - inner and r = truth - inner. The paper's fusion
    is a weighted mean of the two markers, so sigma is held to [0, 1] (``FusionSigmas``); the
    error is a convex quadratic in sigma, so the constrained minimiser is the unconstrained
    one clipped to that range (noise can put it just past 1 when the outer marker is far the
    better one).
    """
    d, r = _residual_pair(outer, inner, truth, circular)
    denominator = float(np.sum(d * d))
    if denominator <= 0.0:
        raise ValueError("the two markers agree exactly: sigma is not determined")
    return min(1.0, max(0.0, float(np.sum(d * r) / denominator)))


def fit_sigma_lms(
    outer: Array,
    inner: Array,
    truth: Array,
    circular: bool = False,
    step: float = 0.5,
    epochs: int = 200,
    tol: float = 1e-9,
    sigma0: float = 0.5,
) -> tuple[float, int]:
    """The paper's iterative Least Mean Squares fit of sigma, minimising E{|e(n)|^2}.

    One normalised LMS update per sample, e(n) = truth - fused, sigma += step * e * d / mean(d^2),
    over the data in order for up to ``epochs`` passes, stopping when a pass moves sigma by less
    than ``tol``. Returns (sigma, passes used). The step is normalised by the data's power so the
    same ``step`` works in centimetres and radians. Each pass ends projected onto [0, 1] (as
    ``fit_sigma_least_squares``), so both fits give weights ``FusionSigmas`` takes.
    """
    d, r = _residual_pair(outer, inner, truth, circular)
    power = float(np.mean(d * d))
    if power <= 0.0:
        raise ValueError("the two markers agree exactly: sigma is not determined")
    mu = step / (power * d.size)
    sigma = sigma0
    for epoch in range(1, epochs + 1):
        before = sigma
        for dn, rn in zip(d, r, strict=True):
            e = rn - sigma * dn
            sigma += mu * e * dn
        sigma = min(1.0, max(0.0, sigma))
        if abs(sigma - before) < tol:
            return sigma, epoch
    return sigma, epochs
