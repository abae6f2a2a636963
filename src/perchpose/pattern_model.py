"""The blurred printed-pattern model of ``perchpose.pattern_fit``, per pixel, compiled.

A pixel at marker coordinates (u, v) sees the pattern's grid of bands blurred separably: each
band's cover along u is a difference of two normal CDFs, likewise along v, and a grid cell's
cover is their product. Only the bands within ``REACH_SIGMAS`` blur widths of the pixel cover
it at all (further, the CDFs differ from 0 and 1 by under 3.2e-5), so each pixel visits the
few bands around it, not the whole grid. ``normal_equations`` sums the Gauss-Newton normal
equations of the fit (the homography's 8 entries, log sigma, the grey levels) over the pixels
without forming the Jacobian; ``fit_pattern`` runs the Gauss-Newton rounds on them.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from perchpose.jit import compiled
from perchpose.step_model import normal_cdf_pdf_at, solve_in_place

Array = NDArray[np.float64]

# bands further from a pixel than this many blur widths do not cover it (their CDFs differ
# from 0 and 1 by under 3.2e-5: a few thousandths of a grey level at a print's contrast, far
# under any image's noise; 4 against 6 widths takes a fifth off the fit's time)
REACH_SIGMAS = 4.0


@compiled
def _window(x: float, lines: Array, reach: float, lo: int) -> tuple[int, int]:
    """The bands [lo, hi) between ``lines`` within ``reach`` of ``x``; the search starts at
    band ``lo`` (the previous pixel's: neighbouring pixels see nearly the same bands)."""
    n_bands = lines.shape[0] - 1
    near = x - reach
    while lo > 0 and lines[lo] > near:
        lo -= 1
    while lo < n_bands - 1 and lines[lo + 1] <= near:
        lo += 1
    hi = lo + 1
    while hi < n_bands and lines[hi] < x + reach:
        hi += 1
    return lo, hi


@compiled
def _merged_bands(
    x: float,
    lines: Array,
    s: float,
    window: tuple[int, int],
    breaks: NDArray[np.bool_],
    across: tuple[int, int],
    out: Array,
    first: NDArray[np.int64],
) -> int:
    """The bands of ``window`` that a point at ``x`` blurred by ``s`` sees, neighbours printed
    alike on every band ``across`` merged into one (``breaks`` (N across, N lines): where the
    print changes at a line): their cover, its derivative by x and by log s written to ``out``
    (3, K), each one's first band to ``first`` (K,). Returns K. Merging is exact: the blur of
    two neighbouring bands printed alike is that of one band spanning both, and it spares the
    CDFs at lines that change nothing within reach (a finer marker's cells, further along)."""
    lo, hi = window
    inv_s = 1.0 / s
    z = (x - lines[lo]) * inv_s
    cdf0, pdf0 = normal_cdf_pdf_at(z)
    k = 0
    start = lo
    for i in range(lo + 1, hi + 1):
        if i < hi:
            changes = False
            for j in range(across[0], across[1]):
                if breaks[j, i]:
                    changes = True
                    break
            if not changes:
                continue
        z1 = (x - lines[i]) * inv_s
        cdf1, pdf1 = normal_cdf_pdf_at(z1)
        out[0, k] = cdf0 - cdf1
        out[1, k] = (pdf0 - pdf1) * inv_s
        out[2, k] = pdf1 * z1 - pdf0 * z
        first[k] = start
        k += 1
        start = i
        z, cdf0, pdf0 = z1, cdf1, pdf1
    return k


@compiled
def _pixel_model(
    basis: Array,
    printed: Array,
    bands_u: Array,
    bands_v: Array,
    first: NDArray[np.int64],
    counts: tuple[int, int],
    rows: Array,
    covers: Array,
) -> tuple[float, float, float, float]:
    """One pixel's modelled grey and its derivatives by u, v and log sigma, from its merged
    bands' covers ``bands_u`` (3, K_u) and ``bands_v`` (3, K_v) (``_merged_bands``; ``counts``
    = (K_u, K_v), ``first`` (2, K) their first grid bands along u and along v) and the grey
    ``printed`` (Nv, Nu) on each grid cell; each basis's cover written to ``covers`` (B,).
    ``rows`` (2, max(Nu, Nv)): scratch."""
    n_u, n_v = counts
    first_u, first_v = first[0], first[1]
    # rows[0, a]: the grey printed along merged band column a, weighted by the covers along
    # v; rows[1, c]: along merged band row c, weighted by the covers along u
    for a in range(n_u):
        rows[0, a] = 0.0
    covers[:] = 0.0
    model = 0.0
    for c in range(n_v):
        j = first_v[c]
        c_j = bands_v[0, c]
        along = 0.0
        for a in range(n_u):
            grey = printed[j, first_u[a]]
            along += grey * bands_u[0, a]
            rows[0, a] += c_j * grey
        rows[1, c] = along
        model += c_j * along
        for b in range(basis.shape[0]):
            row = 0.0
            for a in range(n_u):
                row += basis[b, j, first_u[a]] * bands_u[0, a]
            covers[b] += c_j * row
    dm_du = dm_dv = dm_dls = 0.0
    for a in range(n_u):
        dm_du += rows[0, a] * bands_u[1, a]
        dm_dls += rows[0, a] * bands_u[2, a]
    for c in range(n_v):
        dm_dv += rows[1, c] * bands_v[1, c]
        dm_dls += rows[1, c] * bands_v[2, c]
    return model, dm_du, dm_dv, dm_dls


@compiled
def _print_breaks(basis: Array) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Where the print changes at a line: along u (Nv, Nu + 1), along v (Nu, Nv + 1); the
    outermost lines always count."""
    B, Nv, Nu = basis.shape
    along_u = np.ones((Nv, Nu + 1), np.bool_)
    along_v = np.ones((Nu, Nv + 1), np.bool_)
    for j in range(Nv):
        for i in range(1, Nu):
            same = True
            for b in range(B):
                same = same and basis[b, j, i - 1] == basis[b, j, i]
            along_u[j, i] = not same
    for i in range(Nu):
        for j in range(1, Nv):
            same = True
            for b in range(B):
                same = same and basis[b, j - 1, i] == basis[b, j, i]
            along_v[i, j] = not same
    return along_u, along_v


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
    first = np.zeros((2, max(Nu, Nv)), np.int64)
    breaks_u, breaks_v = _print_breaks(basis)
    rows = np.zeros((2, max(Nu, Nv)))
    printed = np.zeros((Nv, Nu))  # the grey printed on each band cell
    for b in range(B):
        printed += levels[b] * basis[b]
    J = np.zeros(N)
    lo_u = lo_v = 0
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
        lo_u, hi_u = _window(u, lines_u, REACH_SIGMAS * s_u, lo_u)
        lo_v, hi_v = _window(v, lines_v, REACH_SIGMAS * s_v, lo_v)
        n_u = _merged_bands(
            u, lines_u, s_u, (lo_u, hi_u), breaks_u, (lo_v, hi_v), bands_u, first[0]
        )
        n_v = _merged_bands(
            v, lines_v, s_v, (lo_v, hi_v), breaks_v, (lo_u, hi_u), bands_v, first[1]
        )
        model, dm_du, dm_dv, dm_dls = _pixel_model(
            basis, printed, bands_u, bands_v, first, (n_u, n_v), rows, J[9:]
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


@compiled
def fit_pattern(
    q: Array,
    values: Array,
    q_per_px: Array,
    grid: tuple[Array, Array, Array],
    start: tuple[Array, float, Array],
    rounds: tuple[int, Array, float],
) -> tuple[bool, Array, float, Array]:
    """Gauss-Newton on the pattern model (``normal_equations``) of pixels at marker-plane
    points ``q`` (P, 2) of grey ``values`` (P,); ``q_per_px`` (2, 2): d(q)/d(pixel x),
    d(q)/d(pixel y); ``grid``: the print (lines_u, lines_v, basis). From ``start``: the
    homography g (8,), log sigma (the blur in pixels) and the grey levels (B,). ``rounds``:
    (iterations, reach, stop): at most that many rounds; one ends the fit where it moves the
    corners by under ``stop`` (about: the largest change of an entry of g times its ``reach``
    (8,), how far a unit change of it moves a corner) and the blur by under 0.3 %.
    Where the last basis is the off-sheet grey and no pixel sees the sheet's edge in the first
    round, that level is dropped (it could not be fitted). Returns (solved, g, log sigma,
    levels); solved is False where the normal equations were singular."""
    lines_u, lines_v, basis = grid
    g, log_sigma, levels = start[0].copy(), start[1], start[2].copy()
    iterations, reach, stop = rounds
    for it in range(iterations):
        blur_q = math.exp(log_sigma) * q_per_px
        JtJ, Jtr, cover_max = normal_equations(
            q, values, g, blur_q, lines_u, lines_v, basis, levels
        )
        if it == 0 and basis.shape[0] == 3 and not cover_max[2] > 1e-3:
            basis, levels = basis[:2], levels[:2]
            JtJ, Jtr, _ = normal_equations(q, values, g, blur_q, lines_u, lines_v, basis, levels)
        for a in range(Jtr.shape[0]):
            JtJ[a, a] += 1e-9
        if not solve_in_place(JtJ, Jtr):
            return False, g, log_sigma, levels
        step = Jtr
        g -= step[:8]
        log_sigma -= min(0.5, max(-0.5, step[8]))
        levels -= step[9:]
        moved = 0.0
        for a in range(8):
            moved = max(moved, abs(step[a]) * reach[a])
        if moved < stop and abs(step[8]) < 3e-3:
            break
    return True, g, log_sigma, levels
