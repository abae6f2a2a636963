"""The blurred printed-pattern model of ``perchpose.corners.pattern_fit``, per pixel, compiled.

A pixel at marker coordinates (u, v) sees the pattern's grid of bands blurred separably: each
band's cover along u is a difference of two normal CDFs, likewise along v, and a grid cell's
cover is their product. Only the bands within ``REACH_SIGMAS`` blur widths of the pixel cover
it at all (further, the CDFs differ from 0 and 1 by under 3.2e-5), so each pixel visits the
few bands around it, not the whole grid. ``normal_equations`` sums the Gauss-Newton normal
equations of the fit (the homography's 8 entries, log sigma, the grey levels) over the pixels
without forming the Jacobian, tests the residuals for bands over the image rows (analog
interference) and, where asked, eliminates such bands from the equations; ``fit_pattern``
runs the Gauss-Newton rounds on them.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from perchpose.numeric.jit import compiled
from perchpose.numeric.linalg import solve_in_place
from perchpose.numeric.normal import normal_cdf_pdf_at

Array = NDArray[np.float64]

# bands further from a pixel than this many blur widths do not cover it (their CDFs differ
# from 0 and 1 by under 3.2e-5: a few thousandths of a grey level at a print's contrast, far
# under any image's noise; 4 against 6 widths takes a fifth off the fit's time)
REACH_SIGMAS = 4.0
# bands over the rows show along the rows alone: the score test over the rows must be this
# many times that over the columns (on harsh frames with interference it is over 4 times in
# 9 fits of 10; shading, JPEG blocks and a misfit of the model show along both)
ROWS_OVER_COLUMNS = 2.0


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
def _blur_widths(g: Array, blur_q: Array, u: float, v: float, w: float) -> tuple[float, float]:
    """The blur's width along u and along v at cell point (u, v) (homography denominator w):
    d(u, v)/dq, then along pixel x and y."""
    a_ux, a_uy = (g[0] - u * g[6]) / w, (g[1] - u * g[7]) / w
    a_vx, a_vy = (g[3] - v * g[6]) / w, (g[4] - v * g[7]) / w
    s_u = np.hypot(
        a_ux * blur_q[0, 0] + a_uy * blur_q[0, 1], a_ux * blur_q[1, 0] + a_uy * blur_q[1, 1]
    )
    s_v = np.hypot(
        a_vx * blur_q[0, 0] + a_vy * blur_q[0, 1], a_vx * blur_q[1, 0] + a_vy * blur_q[1, 1]
    )
    return s_u, s_v


@compiled
def normal_equations(
    q: Array,
    values: Array,
    g: Array,
    blur_q: Array,
    grid: tuple[Array, Array, Array],
    levels: Array,
    row_bands: tuple[NDArray[np.int64], int, bool],
) -> tuple[Array, Array, Array, tuple[float, float]]:
    """The normal equations (J^T J (N, N), J^T r (N,)) of the pattern model at pixels whose
    marker-plane points are ``q`` (P, 2) and grey ``values`` (P,), N = 9 + B: the homography
    ``g`` (8,) from q to cells (u, v), log sigma and the B ``levels`` of ``grid``'s basis (B,
    Nv, Nu: where each level is printed on the grid of bands between its lines_u (Nu + 1,)
    and lines_v (Nv + 1,)). ``blur_q`` (2, 2): the blur sigma times d(q)/d(pixel x) and
    d(q)/d(pixel y). Also each basis's largest cover of a pixel (B,).

    ``row_bands``: (each pixel's image row and column (P, 2), counted from 0; K;
    eliminate). The grey may have an offset that changes smoothly from row to row (the bands
    of analog interference, or of a rolling shutter under flickering light): the first K
    cosines of the row (cos(pi k (row + 1/2) / rows), k = 1..K) times unknown amplitudes.
    Returns, besides the equations, how much of the squared residuals those cosines would
    take away, over what they would by chance (about 1 without bands), and the same for K
    cosines over the columns (the control: shading, or a misfit of the model, shows along
    both; bands along the rows alone); NaN where K = 0. With eliminate, the amplitudes over
    the rows are eliminated from the equations (they are linear: the equations are those of
    the other parameters at the amplitudes that fit best)."""
    lines_u, lines_v, basis = grid
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
    pixel_of, n_row_bands, eliminate = row_bands
    none = n_row_bands == 0 or pixel_of.shape[0] == 0
    n_rows = 0 if none else int(pixel_of[:, 0].max()) + 1
    n_cols = 0 if none else int(pixel_of[:, 1].max()) + 1
    row_sums = np.zeros((n_rows, N + 3))  # per row: the sums of J, r, 1 and r^2
    col_sums = np.zeros((n_cols, 2))  # per column: the sums of r and 1
    lo_u = lo_v = 0
    for p in range(q.shape[0]):
        qx, qy = q[p, 0], q[p, 1]
        w = g[6] * qx + g[7] * qy + 1.0
        u = (g[0] * qx + g[1] * qy + g[2]) / w
        v = (g[3] * qx + g[4] * qy + g[5]) / w
        s_u, s_v = _blur_widths(g, blur_q, u, v, w)
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
        r = model - values[p]
        _accumulate(JtJ, Jtr, J, r)
        if n_rows > 0:
            _add_to_line(row_sums[pixel_of[p, 0]], col_sums[pixel_of[p, 1]], J, r)
    JtJ = JtJ + np.triu(JtJ, 1).T
    banding = _banding(JtJ, Jtr, (row_sums, col_sums), n_row_bands, eliminate)
    return JtJ, Jtr, cover_max, banding


@compiled
def _banding(
    JtJ: Array, Jtr: Array, sums: tuple[Array, Array], n_bands: int, eliminate: bool
) -> tuple[float, float]:
    """``normal_equations``'s two score tests, from the rows' and the columns' ``sums``
    (``_add_to_line``), with up to ``n_bands`` cosines; with ``eliminate``, the cosines over
    the rows eliminated from the equations."""
    row_sums, col_sums = sums
    n_rows, n_cols = row_sums.shape[0], col_sums.shape[0]
    if n_rows < 2 or n_cols < 2:
        return math.nan, math.nan
    K = min(n_bands, n_rows - 1, n_cols - 1)
    N = row_sums.shape[1] - 3
    along_rows = _row_bands(JtJ, Jtr, row_sums, K, eliminate)
    columns = np.zeros((n_cols, 3))
    columns[:, :2] = col_sums
    along_columns = _row_bands(JtJ, Jtr, columns, K, False) * _chance(row_sums, N, K)
    return along_rows, along_columns


@compiled
def _add_to_line(sums: Array, column_sums: Array, J: Array, r: float) -> None:
    """Adds a pixel's Jacobian row ``J`` (N,) and residual ``r`` to its image row's ``sums``
    (N + 3,: of J, r, 1 and r^2) and its column's (2,: of r and 1)."""
    N = J.shape[0]
    for a in range(N):
        sums[a] += J[a]
    sums[N] += r
    sums[N + 1] += 1.0
    sums[N + 2] += r * r
    column_sums[0] += r
    column_sums[1] += 1.0


@compiled
def _row_bands(JtJ: Array, Jtr: Array, row_sums: Array, K: int, eliminate: bool) -> float:
    """How many times more of the squared residuals K cosines over the rows would take away
    than they would by chance (a score test), from each row's sums of J, r, 1 and r^2
    (``row_sums``, (rows, N + 3)); with ``eliminate``, the normal equations with the
    cosines' amplitudes eliminated (their Schur complement). NaN where the cosines cannot be
    told apart over these rows."""
    n_rows, N = row_sums.shape[0], row_sums.shape[1] - 3
    G = np.zeros((K, K))  # sum of phi phi^T over the pixels
    A = np.zeros((K, N + 1))  # sum of phi J^T, and of phi r in the last column
    phi = np.empty(K)
    for row in range(n_rows):
        for k in range(K):
            phi[k] = math.cos(math.pi * (k + 1) * (row + 0.5) / n_rows)
        for k in range(K):
            for m in range(K):
                G[k, m] += row_sums[row, N + 1] * phi[k] * phi[m]
            for a in range(N + 1):
                A[k, a] += phi[k] * row_sums[row, a]
    X = np.empty((K, N + 1))  # G^-1 A
    for a in range(N + 1):
        column = A[:, a].copy()
        if not solve_in_place(G.copy(), column):
            return math.nan
        X[:, a] = column
    if eliminate:
        _eliminate(JtJ, Jtr, A, X)
    explained = 0.0
    for k in range(K):
        explained += A[k, N] * X[k, N]
    if N == 0:  # no Jacobian sums: the explained squares alone
        return explained
    return explained * _chance(row_sums, N, K)


@compiled
def _chance(row_sums: Array, N: int, K: int) -> float:
    """1 / (K times the residuals' variance): what K cosines take away by chance, inverted,
    from the rows' sums of r, 1 and r^2 (the last 3 columns of ``row_sums``)."""
    dof = np.sum(row_sums[:, N + 1]) - N - K
    squares = np.sum(row_sums[:, N + 2])
    if not (dof > 0 and squares > 0):
        return math.nan
    return float(dof / squares / K)


@compiled
def banded(banding: tuple[float, float], above: float) -> bool:
    """Whether the residuals show bands over the rows (``normal_equations``'s two ratios):
    over ``above`` along the rows, and over ``ROWS_OVER_COLUMNS`` times what they show along
    the columns."""
    rows, columns = banding
    return rows > above and rows > ROWS_OVER_COLUMNS * columns


@compiled
def _eliminate(JtJ: Array, Jtr: Array, A: Array, X: Array) -> None:
    """Subtracts A^T X from the normal equations (the last column of A and X: the
    residuals')."""
    K, N = A.shape[0], A.shape[1] - 1
    for a in range(N):
        for c in range(N):
            for k in range(K):
                JtJ[a, c] -= A[k, a] * X[k, c]
        for k in range(K):
            Jtr[a] -= A[k, a] * X[k, N]


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
    row_bands: tuple[NDArray[np.int64], int, float],
) -> tuple[bool, Array, float, Array, tuple[float, float]]:
    """Gauss-Newton on the pattern model (``normal_equations``) of pixels at marker-plane
    points ``q`` (P, 2) of grey ``values`` (P,); ``q_per_px`` (2, 2): d(q)/d(pixel x),
    d(q)/d(pixel y); ``grid``: the print (lines_u, lines_v, basis). From ``start``: the
    homography g (8,), log sigma (the blur in pixels) and the grey levels (B,). ``rounds``:
    (iterations, reach, stop): at most that many rounds; one ends the fit where it moves the
    corners by under ``stop`` (about: the largest change of an entry of g times its ``reach``
    (8,), how far a unit change of it moves a corner) and the blur by under 0.3 %.
    Where the last basis is the off-sheet grey and no pixel sees the sheet's edge in the first
    round, that level is dropped (it could not be fitted). ``row_bands``: each pixel's image
    row, how many cosines over the rows the grey may have (``normal_equations``) and
    banded_above: where the fit without them ends with residuals that they would take over
    banded_above times as much of as chance would, it goes on with them for as many rounds
    again (0: with them from the first round). Also returns that ratio, at the fit's last
    round (the cosines' amplitudes are never part of the model's residuals: with them
    eliminated the ratio still measures the bands).
    Returns (solved, g, log sigma, levels, that ratio); solved is False where the normal
    equations were singular."""
    lines_u, lines_v, basis = grid
    g, log_sigma, levels = start[0].copy(), start[1], start[2].copy()
    iterations, reach, stop = rounds
    row_of, n_row_bands, banded_above = row_bands
    eliminate = not banded_above > 0
    banding = (math.nan, math.nan)
    it = 0
    while it < iterations:
        blur_q = math.exp(log_sigma) * q_per_px
        how = (row_of, n_row_bands, eliminate)
        JtJ, Jtr, cover_max, banding = normal_equations(
            q, values, g, blur_q, (lines_u, lines_v, basis), levels, how
        )
        if it == 0 and not eliminate and basis.shape[0] == 3 and not cover_max[2] > 1e-3:
            basis, levels = basis[:2], levels[:2]
            JtJ, Jtr, _, banding = normal_equations(
                q, values, g, blur_q, (lines_u, lines_v, basis), levels, how
            )
        for a in range(Jtr.shape[0]):
            JtJ[a, a] += 1e-9
        if not solve_in_place(JtJ, Jtr):
            return False, g, log_sigma, levels, banding
        step = Jtr
        g -= step[:8]
        log_sigma -= min(0.5, max(-0.5, step[8]))
        levels -= step[9:]
        moved = 0.0
        for a in range(8):
            moved = max(moved, abs(step[a]) * reach[a])
        it += 1
        if (moved < stop and abs(step[8]) < 3e-3) or it == iterations:
            if eliminate or not banded(banding, banded_above):
                break
            eliminate, it = True, 0
    return True, g, log_sigma, levels, banding
