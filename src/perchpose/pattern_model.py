"""The blurred printed-pattern model of ``perchpose.pattern_fit``, per pixel, compiled.

A pixel at marker coordinates (u, v) sees the pattern's grid of bands blurred separably: each
band's cover along u is a difference of two normal CDFs, likewise along v, and a grid cell's
cover is their product. Only the bands within ``REACH_SIGMAS`` blur widths of the pixel cover
it at all (further, the CDFs differ from 0 and 1 by under 3.2e-5), so each pixel visits the
few bands around it, not the whole grid. ``normal_equations`` sums the Gauss-Newton normal
equations of the fit (the homography's 8 entries, log sigma, the grey levels) over the pixels
without forming the Jacobian.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from perchpose.jit import compiled
from perchpose.step_model import normal_cdf_pdf_at

Array = NDArray[np.float64]

# bands further from a pixel than this many blur widths do not cover it (their CDFs differ
# from 0 and 1 by under 3.2e-5: a few thousandths of a grey level at a print's contrast, far
# under any image's noise; 4 against 6 widths takes a fifth off the fit's time)
REACH_SIGMAS = 4.0


@compiled
def _bands_at(x: float, lines: Array, s: float, out: Array) -> tuple[int, int]:
    """The bands [lo, hi) between ``lines`` that a point at ``x`` blurred by ``s`` sees, with
    their cover, its derivative by x and by log s written to ``out`` (3, N) at those
    indices."""
    n_bands = lines.shape[0] - 1
    lo = 0
    while lo < n_bands - 1 and lines[lo + 1] <= x - REACH_SIGMAS * s:
        lo += 1
    hi = lo + 1
    while hi < n_bands and lines[hi] < x + REACH_SIGMAS * s:
        hi += 1
    inv_s = 1.0 / s
    z = (x - lines[lo]) * inv_s
    cdf0, pdf0 = normal_cdf_pdf_at(z)
    for i in range(lo, hi):
        z1 = (x - lines[i + 1]) * inv_s
        cdf1, pdf1 = normal_cdf_pdf_at(z1)
        out[0, i] = cdf0 - cdf1
        out[1, i] = (pdf0 - pdf1) * inv_s
        out[2, i] = pdf1 * z1 - pdf0 * z
        z, cdf0, pdf0 = z1, cdf1, pdf1
    return lo, hi


@compiled
def _pixel_model(
    basis: Array,
    printed: Array,
    bands_u: Array,
    bands_v: Array,
    bounds: tuple[int, int, int, int],
    rows: Array,
    covers: Array,
) -> tuple[float, float, float, float]:
    """One pixel's modelled grey and its derivatives by u, v and log sigma, from its bands'
    covers ``bands_u`` (3, Nu) and ``bands_v`` (3, Nv) (``_bands_at``) within ``bounds``
    (lo_u, hi_u, lo_v, hi_v) and the grey ``printed`` (Nv, Nu) on each band cell; each
    basis's cover written to ``covers`` (B,). ``rows`` (2, max(Nu, Nv)): scratch."""
    lo_u, hi_u, lo_v, hi_v = bounds
    # rows[0, i]: the grey printed along band column i, weighted by the covers along v;
    # rows[1, j]: along band row j, weighted by the covers along u
    for i in range(lo_u, hi_u):
        rows[0, i] = 0.0
    covers[:] = 0.0
    model = 0.0
    for j in range(lo_v, hi_v):
        c_j = bands_v[0, j]
        along = 0.0
        for i in range(lo_u, hi_u):
            along += printed[j, i] * bands_u[0, i]
            rows[0, i] += c_j * printed[j, i]
        rows[1, j] = along
        model += c_j * along
        for b in range(basis.shape[0]):
            row = 0.0
            for i in range(lo_u, hi_u):
                row += basis[b, j, i] * bands_u[0, i]
            covers[b] += c_j * row
    dm_du = dm_dv = dm_dls = 0.0
    for i in range(lo_u, hi_u):
        dm_du += rows[0, i] * bands_u[1, i]
        dm_dls += rows[0, i] * bands_u[2, i]
    for j in range(lo_v, hi_v):
        dm_dv += rows[1, j] * bands_v[1, j]
        dm_dls += rows[1, j] * bands_v[2, j]
    return model, dm_du, dm_dv, dm_dls


@compiled
def normal_equations(
    q: Array,
    values: Array,
    g: Array,
    blur_q: Array,
    lines_u: Array,
    lines_v: Array,
    basis: Array,
    levels: Array,
) -> tuple[Array, Array, Array]:
    """The normal equations (J^T J (N, N), J^T r (N,)) of the pattern model at pixels whose
    marker-plane points are ``q`` (P, 2) and grey ``values`` (P,), N = 9 + B: the homography
    ``g`` (8,) from q to cells (u, v), log sigma and the B ``levels`` of ``basis`` (B, Nv, Nu:
    where each level is printed on the grid of bands between ``lines_u`` (Nu + 1,) and
    ``lines_v`` (Nv + 1,)). ``blur_q`` (2, 2): the blur sigma times d(q)/d(pixel x) and
    d(q)/d(pixel y). Also each basis's largest cover of a pixel (B,)."""
    B, Nv, Nu = basis.shape
    N = 9 + B
    JtJ = np.zeros((N, N))
    Jtr = np.zeros(N)
    cover_max = np.zeros(B)
    bands_u, bands_v = np.zeros((3, Nu)), np.zeros((3, Nv))
    rows = np.zeros((2, max(Nu, Nv)))
    printed = np.zeros((Nv, Nu))  # the grey printed on each band cell
    for b in range(B):
        printed += levels[b] * basis[b]
    J = np.zeros(N)
    for p in range(q.shape[0]):
        qx, qy = q[p, 0], q[p, 1]
        w = g[6] * qx + g[7] * qy + 1.0
        u = (g[0] * qx + g[1] * qy + g[2]) / w
        v = (g[3] * qx + g[4] * qy + g[5]) / w
        # d(u, v)/dq, then along pixel x and y: the blur's width along u and along v
        a_ux, a_uy = (g[0] - u * g[6]) / w, (g[1] - u * g[7]) / w
        a_vx, a_vy = (g[3] - v * g[6]) / w, (g[4] - v * g[7]) / w
        s_u = np.hypot(
            a_ux * blur_q[0, 0] + a_uy * blur_q[0, 1], a_ux * blur_q[1, 0] + a_uy * blur_q[1, 1]
        )
        s_v = np.hypot(
            a_vx * blur_q[0, 0] + a_vy * blur_q[0, 1], a_vx * blur_q[1, 0] + a_vy * blur_q[1, 1]
        )
        lo_u, hi_u = _bands_at(u, lines_u, s_u, bands_u)
        lo_v, hi_v = _bands_at(v, lines_v, s_v, bands_v)
        model, dm_du, dm_dv, dm_dls = _pixel_model(
            basis, printed, bands_u, bands_v, (lo_u, hi_u, lo_v, hi_v), rows, J[9:]
        )
        J[0], J[1], J[2] = dm_du * qx / w, dm_du * qy / w, dm_du / w
        J[3], J[4], J[5] = dm_dv * qx / w, dm_dv * qy / w, dm_dv / w
        turn = -(dm_du * u + dm_dv * v) / w
        J[6], J[7], J[8] = turn * qx, turn * qy, dm_dls
        for b in range(B):
            cover_max[b] = max(cover_max[b], J[9 + b])
        _accumulate(JtJ, Jtr, J, model - values[p])
    return JtJ + np.triu(JtJ, 1).T, Jtr, cover_max


@compiled
def _accumulate(JtJ: Array, Jtr: Array, J: Array, r: float) -> None:
    """Adds one pixel's Jacobian row ``J`` and residual ``r`` to the normal equations (the
    upper triangle of ``JtJ``)."""
    N = J.shape[0]
    for a in range(N):
        Jtr[a] += J[a] * r
        for c in range(a, N):
            JtJ[a, c] += J[a] * J[c]
