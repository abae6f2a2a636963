"""The blurred-step model of a marker's border edges and its Gauss-Newton fit, compiled.

``perchpose.corners.edge_fit`` samples K profiles across a marker's sides and fits them all at once
with ``a + b * F(s - d_k)`` (F a step blurred by a Gaussian of ``sigma`` and integrated over
the pixel), one edge offset ``d_k`` per profile and the levels, contrasts, the margin's drop
and log sigma shared. This module holds that fit's arithmetic: the pixel-integrated step
(through ``perchpose.numeric.normal``) and the Gauss-Newton rounds, each a loop over the
samples (``perchpose.numeric.jit``); ``corners`` prepares the data and reads the result.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from perchpose.numeric.jit import compiled
from perchpose.numeric.linalg import solve_in_place
from perchpose.numeric.normal import normal_cdf_pdf_at

Array = NDArray[np.float64]

# grey levels between dark and light under which there is no edge (or pattern) to fit
MIN_CONTRAST = 4.0
# bounds of the fitted optical blur sigma, px
MIN_BLUR_PX, MAX_BLUR_PX = 0.05, 6.0
_LOG_MIN_BLUR, _LOG_MAX_BLUR = math.log(MIN_BLUR_PX), math.log(MAX_BLUR_PX)
# steps shrink about tenfold a round: after steps this small the edges would move ~1e-3 px
_SETTLED = 8e-3


@compiled
def pixel_step(t: float, sigma: float) -> tuple[float, float, float]:
    """A unit step at 0 blurred by a Gaussian of ``sigma`` and integrated over a pixel 1 wide,
    at ``t`` (px): ``sigma * (psi((t + 1/2) / sigma) - psi((t - 1/2) / sigma))`` with
    ``psi(x) = x Phi(x) + phi(x)``; and its derivatives by t and by log sigma. (A pixel turned
    to the edge projects onto its normal as a trapezoid of the same variance, 1/12.)"""
    a = (t + 0.5) * (1.0 / sigma)
    b = (t - 0.5) * (1.0 / sigma)
    cdf_a, pdf_a = normal_cdf_pdf_at(a)
    cdf_b, pdf_b = normal_cdf_pdf_at(b)
    value = sigma * (a * cdf_a + pdf_a - b * cdf_b - pdf_b)
    return value, cdf_a - cdf_b, sigma * (pdf_a - pdf_b)


@compiled
def profile_start(values: Array, offsets: Array) -> tuple[float, float, Array, float]:
    """Where the fit of profiles ``values`` (K, M, sampled at ``offsets`` (M,), dark to
    light) starts: the dark and light levels (the means of each profile's first and last
    quarter of samples), each profile's crossing of the level halfway between (linear
    interpolation; the crossing nearest the middle where noise makes several, 0 where none),
    and the profiles' mean steepest rise between neighbouring samples."""
    K, M = values.shape
    quarter = max(1, M // 4)
    lo = hi = 0.0
    for k in range(K):
        for m in range(quarter):
            lo += values[k, m]
            hi += values[k, M - quarter + m]
    lo /= K * quarter
    hi /= K * quarter
    level = lo + 0.5 * (hi - lo)
    d = np.zeros(K)
    rise = 0.0
    for k in range(K):
        nearest = np.inf
        steepest = -np.inf
        for m in range(M - 1):
            v0, v1 = values[k, m], values[k, m + 1]
            steepest = max(steepest, v1 - v0)
            if (v0 >= level) != (v1 >= level):
                frac = min(max((level - v0) / (v1 - v0), 0.0), 1.0)
                position = offsets[m] + frac * (offsets[m + 1] - offsets[m])
                if abs(position) < nearest:
                    nearest = abs(position)
                    d[k] = position
        rise += steepest
    return lo, hi, d, rise / K


@compiled
def _pixel_model(
    t: float,
    sigma: float,
    levels: tuple[float, float, float],
    surround: tuple[float, float, float],
    with_margin: bool,
) -> tuple[float, float, float, float, float]:
    """The step model at a pixel ``t`` px from the edge: (the blurred step G, the model's
    derivative by the edge, by log sigma and by the margin's drop, the model itself).
    ``levels``: the dark level, the contrast and the margin's drop; ``surround``: 1 where
    the cell inside the border is white (else 0), how far inside its edge lies and where the
    margin ends (px, ``fit_steps``)."""
    a, b, drop = levels
    white, inner, margin = surround
    step, slope, dG_ds = pixel_step(t, sigma)
    dG_dd = -slope
    if white != 0.0:
        F2, slope2, ds2 = pixel_step(t + inner, sigma)
        step = step + white * (1.0 - F2)
        dG_dd = dG_dd + white * slope2
        dG_ds = dG_ds - white * ds2
    j = b * dG_dd
    J_s = b * dG_ds
    model = a + b * step
    x_drop = 0.0
    if with_margin:
        F3, slope3, ds3 = pixel_step(t - margin, sigma)
        model = model - drop * F3
        j = j + drop * slope3
        J_s = J_s - drop * ds3
        x_drop = -F3
    return step, j, J_s, x_drop, model


@compiled
def _model_sums(
    pixels: Array,
    d: Array,
    W: Array,
    levels: Array,
    sigma: float,
    surround: Array,
    drop: float,
    with_margin: bool,
) -> tuple[Array, Array]:
    """The step model at every pixel of weight over 0, summed per profile into what the
    normal equations are made of (one pass over the pixels): (K, 9) the weighted sums of G,
    G^2, r, G r, J_d times 1, G, J_d, r, and the weights; (K, X, 4 + X) of each extra x
    times 1, G, r, J_d, then each extra. G is the blurred step, J_d its derivative by the
    profile's edge, the extras the derivatives by the shared parameters beyond the levels
    (the margin's drop when fitted, then log sigma), r the residual."""
    at, data, weight = pixels[0], pixels[1], pixels[2]
    K, M = at.shape
    R = W.shape[0]
    X = 2 if with_margin else 1
    sums = np.zeros((K, 9))
    x_sums = np.zeros((K, X, 4 + X))  # x, x G, x r, x J_d, then x times each extra
    xs = np.empty(X)
    for k in range(K):
        a = 0.0
        b = 0.0
        for q in range(R):
            a += levels[0, q] * W[q, k]
            b += levels[1, q] * W[q, k]
        white, inner, margin = surround[0, k], surround[1, k], surround[2, k]
        for m in range(M):
            w_km = weight[k, m]
            if w_km == 0.0:
                continue
            g_km, j_km, J_s, x_drop, model = _pixel_model(
                at[k, m] - d[k], sigma, (a, b, drop), (white, inner, margin), with_margin
            )
            if with_margin:
                xs[0] = x_drop
            xs[X - 1] = J_s
            r_km = model - data[k, m]
            sums[k, 8] += w_km
            wg, wj = w_km * g_km, w_km * j_km
            sums[k, 0] += wg
            sums[k, 1] += wg * g_km
            sums[k, 2] += w_km * r_km
            sums[k, 3] += wg * r_km
            sums[k, 4] += wj
            sums[k, 5] += wj * g_km
            sums[k, 6] += wj * j_km
            sums[k, 7] += wj * r_km
            for i in range(X):
                wx = w_km * xs[i]
                x_sums[k, i, 0] += wx
                x_sums[k, i, 1] += wx * g_km
                x_sums[k, i, 2] += wx * r_km
                x_sums[k, i, 3] += wx * j_km
                for j in range(X):
                    x_sums[k, i, 4 + j] += wx * xs[j]
    return sums, x_sums


@compiled
def _normal_equations(
    sums: Array, x_sums: Array, W: Array
) -> tuple[Array, Array, Array, Array, Array]:
    """The Gauss-Newton normal equations of the step model from the per-profile sums of
    ``_model_sums``, in two parts: the shared parameters' own block E (P, P) and gradient
    g (P,) (levels, contrasts, then the extras), each profile's coupling to them C (K, P),
    and its own edge's curvature D and gradient g_d (K,)."""
    K = sums.shape[0]
    R = W.shape[0]
    X = x_sums.shape[1]
    P = 2 * R + X
    E = np.zeros((P, P))
    g = np.zeros(P)
    C = np.zeros((K, P))
    for k in range(K):
        for q in range(R):
            w_q = W[q, k]
            C[k, q] = sums[k, 4] * w_q
            C[k, R + q] = sums[k, 5] * w_q
            g[q] += sums[k, 2] * w_q
            g[R + q] += sums[k, 3] * w_q
            for p in range(R):
                ww = w_q * W[p, k]
                E[q, p] += sums[k, 8] * ww
                E[q, R + p] += sums[k, 0] * ww
                E[R + q, R + p] += sums[k, 1] * ww
            for i in range(X):
                E[q, 2 * R + i] += x_sums[k, i, 0] * w_q
                E[R + q, 2 * R + i] += x_sums[k, i, 1] * w_q
        for i in range(X):
            C[k, 2 * R + i] = x_sums[k, i, 3]
            g[2 * R + i] += x_sums[k, i, 2]
            for j in range(X):
                E[2 * R + i, 2 * R + j] += x_sums[k, i, 4 + j]
    for i in range(P):  # symmetric: the lower triangle from the upper
        for j in range(i):
            E[i, j] = E[j, i]
    return E, g, C, sums[:, 6] + 1e-12, sums[:, 7].copy()


@compiled
def _schur_step(E: Array, g: Array, C: Array, D: Array, g_d: Array) -> tuple[bool, Array, Array]:
    """(solved, the shared parameters' step, each profile's own edge step), through the Schur
    complement of the shared parameters; not solved where the equations are singular."""
    K, P = C.shape
    S = E.copy()
    rhs = g.copy()
    for k in range(K):
        for i in range(P):
            c_i = C[k, i] / D[k]
            rhs[i] -= c_i * g_d[k]
            for j in range(P):
                S[i, j] -= c_i * C[k, j]
    step_d = np.empty(K)
    if not solve_in_place(S, rhs):
        return False, rhs, step_d
    for k in range(K):
        s = g_d[k]
        for i in range(P):
            s -= C[k, i] * rhs[i]
        step_d[k] = s / D[k]
    return True, rhs, step_d


@compiled
def fit_steps(
    pixels: Array,
    d: Array,
    W: Array,
    levels: Array,
    log_sigma: float,
    surround: Array,
    with_margin: bool,
    iterations: int,
) -> tuple[bool, float]:
    """Gauss-Newton on the step model of K profiles: ``pixels`` (3, K, M) their pixels'
    offsets across the edge (px), grey values and weights (least squares weighted by them;
    ``edge_geometry.sample_profiles``' counts, 0 for a pixel left out). Updated in place
    from their first values: the edges ``d`` (K,) and ``levels`` (2, R: dark levels,
    contrasts) of the design ``W`` (R, K: a profile's dark level is ``W[:, k] . levels[0]``).
    ``surround`` (3, K): 1 where the cell inside the border is white (else 0), how far inside
    the border's inner edge lies, and where the white margin outside ends (px), a third step
    fitted with its own drop ``with_margin``. Returns (whether the fit holds: finite edges and
    every contrast positive, the blur sigma's log).

    Each d_k touches only its own profile and each level only its group's, so the normal
    equations are assembled from per-profile sums and solved through the Schur complement of
    the shared parameters (levels, contrasts, the margin's drop when fitted, log sigma)."""
    R = W.shape[0]
    drop = 0.0
    for _ in range(iterations):
        sums, x_sums = _model_sums(
            pixels, d, W, levels, math.exp(log_sigma), surround, drop, with_margin
        )
        solved, step, step_d = _schur_step(*_normal_equations(sums, x_sums, W))
        if not solved:
            return False, log_sigma
        for k in range(d.shape[0]):
            d[k] -= min(1.0, max(-1.0, step_d[k]))
        for q in range(R):
            levels[0, q] -= step[q]
            levels[1, q] -= step[R + q]
        if with_margin:
            drop -= step[2 * R]
        step_s = min(0.5, max(-0.5, step[-1]))
        log_sigma = min(_LOG_MAX_BLUR, max(_LOG_MIN_BLUR, log_sigma - step_s))
        if np.max(np.abs(step_d)) < _SETTLED and abs(step_s) < _SETTLED:
            break
    # every profile's contrast positive (a loop: numba's matrix product needs scipy's BLAS,
    # which a plain install does not bring)
    for k in range(d.shape[0]):
        contrast = 0.0
        for q in range(R):
            contrast += levels[1, q] * W[q, k]
        if not (math.isfinite(d[k]) and contrast > 0.0):
            return False, log_sigma
    return True, log_sigma
