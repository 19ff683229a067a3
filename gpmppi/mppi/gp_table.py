"""The GP residual table of the rollouts: the ensemble collapse and its interpolation (multilinear, simplex).

`collapse_table` re-weights the model's (G, G, G, G, 4M) grid table with the current terrain weights
into a (G, G, G, G, 4) float32 table [mean_v, mean_w, var_v, var_w]; the planner collapses it lazily
instead, slab by slab as the rollouts reach them (`gpmppi.mppi.lazy_collapse`; on CUDA the host's copy, for the
nominal, while the device collapses its own whole). `interp4` / `interp4_simplex` read it at a GP input.
The rollout kernels inline these.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from gpmppi.gp.grid_interp import grid_cell
from gpmppi.kernel_flags import FASTMATH, fmax, fmin

TABLE_AXES = np.array([2, 3, 0, 1])  # collapsed table axes in terms of the GP input [v_ref, omega_ref, v, omega]


def rollout_order(table: np.ndarray) -> np.ndarray:
    """The model's (G,G,G,G,4M) grid table with its axes in `TABLE_AXES` order, float32, contiguous.

    A rollout's velocities change slowly from step to step while its noisy commands jump, so with
    the velocity axes outermost consecutive lookups of one sample stay within a few planes of the
    table. Done once per planner: collapsing from this order reads and writes in one stream
    (collapsing with the transposition inside wrote with a large stride and took 2x as long).
    """
    return np.ascontiguousarray(np.transpose(table, (2, 3, 0, 1, 4)), dtype=np.float32)


def terrain_rows(ordered: np.ndarray) -> np.ndarray:
    """The `rollout_order` table as (nodes, 4M) float32 rows, each terrain's four values side by side:
    [mean_v, mean_w, var_v, var_w] of terrain 0, of terrain 1, ... (the collapse then weighs four adjacent
    values by four adjacent factors, which compiles to vector code)."""
    g = ordered.shape
    m = g[4] // 4
    grouped = ordered.reshape(-1, 2, m, 2).transpose(0, 2, 1, 3)  # (nodes, terrain, mean|var, v|w)
    return np.ascontiguousarray(grouped.reshape(-1, 4 * m), dtype=np.float32)


def collapse_weights(weights: np.ndarray, noise: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """The collapse's factors (4 + 4M,): the starting values [0, 0, n_v, n_w], then per terrain [w, w, w^2, w^2]."""
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    factors = np.column_stack([w, w, w * w, w * w]).reshape(-1)
    return np.concatenate([[0.0, 0.0, float(noise[0]), float(noise[1])], factors])


def collapse_table(
    table: np.ndarray, weights: np.ndarray, noise: tuple[float, float] = (0.0, 0.0), ordered: bool = False
) -> np.ndarray:
    """(G,G,G,G,4M) table -> (G,G,G,G,4) float32 [sum w m_v, sum w m_w, sum w^2 C_v + n_v, sum w^2 C_w + n_w].

    `table` is the model's grid table, or (`ordered=True`) its `rollout_order` copy; the output's axes
    are in `TABLE_AXES` order either way. `noise` (n_v, n_w) is added to the two variance channels.
    """
    src = table if ordered else rollout_order(table)
    # allocated by numpy, which asks the kernel for huge pages on large arrays: the rollouts read
    # this table at random, and huge pages mean fewer TLB misses
    out = np.empty(src.shape[:4] + (4,), dtype=np.float32)
    collapse_into(terrain_rows(src), collapse_weights(weights, noise), out.reshape(-1, 4))
    return out


@njit(cache=True, nogil=True, _nrt=False)
def collapse_rows(src: np.ndarray, collapse_w: np.ndarray, out: np.ndarray, start: int, stop: int) -> None:
    """Rows start .. stop - 1 of the collapsed table from the `terrain_rows` rows `src` and the
    `collapse_weights` factors: out[i, c] = start_c + sum over terrains t of factor_tc src[i, 4t + c], summed in
    terrain order in float64 (whoever collapses a row on the CPU, lazily or whole, gets the same bits; the CUDA
    twin's fused multiply-adds may differ in the last bit)."""
    m = src.shape[1] // 4
    for i in range(start, stop):
        a0 = collapse_w[0]
        a1 = collapse_w[1]
        a2 = collapse_w[2]
        a3 = collapse_w[3]
        for t in range(m):
            k = 4 * t
            a0 += collapse_w[4 + k] * src[i, k]
            a1 += collapse_w[5 + k] * src[i, k + 1]
            a2 += collapse_w[6 + k] * src[i, k + 2]
            a3 += collapse_w[7 + k] * src[i, k + 3]
        out[i, 0] = a0
        out[i, 1] = a1
        out[i, 2] = a2
        out[i, 3] = a3


_CHUNK = 4096  # rows per task of the whole collapse


@njit(cache=True, parallel=True)
def collapse_into(src: np.ndarray, collapse_w: np.ndarray, out: np.ndarray) -> None:
    """The whole (nodes, 4) collapsed table into `out` (`collapse_rows` over every row, in parallel)."""
    n = src.shape[0]
    for c in prange((n + _CHUNK - 1) // _CHUNK):
        collapse_rows(src, collapse_w, out, c * _CHUNK, min(n, (c + 1) * _CHUNK))


@njit(cache=True, fastmath=FASTMATH, inline="always")
def interp4(
    table: np.ndarray, dims: np.ndarray, lo: np.ndarray, inv_step: np.ndarray, a0: float, a1: float, a2: float,
    a3: float,
) -> tuple[float, float, float, float]:
    """Multilinear interpolation of a (G0*G1*G2*G3, 4) float32 table with grid `dims` (clamped at the faces).

    Flat node indices and single-precision accumulation (no float64 conversion of the 64 loaded
    values); a (nodes, 4) table measured faster here than a 1-D one.
    """
    i0, f0 = grid_cell(a0, lo[0], inv_step[0], dims[0])
    i1, f1 = grid_cell(a1, lo[1], inv_step[1], dims[1])
    i2, f2 = grid_cell(a2, lo[2], inv_step[2], dims[2])
    i3, f3 = grid_cell(a3, lo[3], inv_step[3], dims[3])
    s2 = dims[3]
    s1 = dims[2] * s2
    s0 = dims[1] * s1
    base = i0 * s0 + i1 * s1 + i2 * s2 + i3
    g0 = np.float32(f0)
    g1 = np.float32(f1)
    g2 = np.float32(f2)
    g3 = np.float32(f3)
    one = np.float32(1.0)
    e0 = one - g0
    e1 = one - g1
    e2 = one - g2
    e3 = one - g3
    c0 = np.float32(0.0)
    c1 = np.float32(0.0)
    c2 = np.float32(0.0)
    c3 = np.float32(0.0)
    # 8 pairs of nodes adjacent along the last axis
    for b in range(8):
        b0 = b >> 2
        b1 = (b >> 1) & 1
        b2 = b & 1
        w = (g0 if b0 else e0) * (g1 if b1 else e1) * (g2 if b2 else e2)
        lo_w = w * e3
        hi_w = w * g3
        n = base + b0 * s0 + b1 * s1 + b2 * s2
        c0 += lo_w * table[n, 0] + hi_w * table[n + 1, 0]
        c1 += lo_w * table[n, 1] + hi_w * table[n + 1, 1]
        c2 += lo_w * table[n, 2] + hi_w * table[n + 1, 2]
        c3 += lo_w * table[n, 3] + hi_w * table[n + 1, 3]
    return float(c0), float(c1), float(c2), float(c3)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _cswap(fa: float, sa: int, fb: float, sb: int) -> tuple[float, int, float, int]:
    """Order two (fraction, stride) pairs by descending fraction.

    Written as selects, not a branch: the fractions are random, a branch would mispredict half the time.
    """
    swap = fb > fa
    # selects, not max/min: numba's CUDA target cannot compile float max/min
    return fmax(fa, fb), sb if swap else sa, fmin(fa, fb), sa if swap else sb


_F32_ZERO = np.float32(0.0)
_F32_ONE = np.float32(1.0)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def cell32(
    x: float, lo: np.float32, inv_step: np.float32, top: np.float32, last: np.int32
) -> tuple[np.int32, np.float32]:
    """Cell index and fraction of `x` along one axis (as `grid_cell`), in single precision.

    `top` = nodes - 1, `last` = nodes - 2. float32 and int32 so that a group of samples fills a
    vector register twice as wide as in double precision; the fraction's rounding (~2e-6 of a cell
    on a 30-node axis) is far below the interpolation's own error.
    """
    t = (np.float32(x) - lo) * inv_step
    # selects written so that NaN fails both tests and lands on node 0: a NaN state (an overflowed rollout)
    # then reads inside the table instead of at a garbage index
    t = t if t > _F32_ZERO else _F32_ZERO
    t = t if t < top else top
    i = np.int32(t)
    i = i if i < last else last
    return i, t - np.float32(i)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def simplex_corner(
    grid: tuple, a0: float, a1: float, a2: float, a3: float
) -> tuple[np.int32, np.int32, np.int32, np.int32, np.int32, np.float32, np.float32, np.float32, np.float32,
           np.float32]:
    """First node, the 4 strides to the next vertices, and the 5 barycentric weights of the point's Kuhn simplex.

    `grid`: the grid's parameters as single-precision scalars (`simplex_params`); scalars only, no arrays, no
    branches: a loop over a group of samples calling it compiles to vector code.
    """
    (lo0, lo1, lo2, lo3, inv0, inv1, inv2, inv3, top0, top1, top2, top3, last0, last1, last2, last3, s0, s1,
     s2) = grid
    i0, f0 = cell32(a0, lo0, inv0, top0, last0)
    i1, f1 = cell32(a1, lo1, inv1, top1, last1)
    i2, f2 = cell32(a2, lo2, inv2, top2, last2)
    i3, f3 = cell32(a3, lo3, inv3, top3, last3)
    t0 = s0
    t1 = s1
    t2 = s2
    t3 = np.int32(1)
    n0 = i0 * s0 + i1 * s1 + i2 * s2 + i3
    # sorting network for 4 elements (5 compare-exchanges), descending by fraction
    f0, t0, f1, t1 = _cswap(f0, t0, f1, t1)
    f2, t2, f3, t3 = _cswap(f2, t2, f3, t3)
    f0, t0, f2, t2 = _cswap(f0, t0, f2, t2)
    f1, t1, f3, t3 = _cswap(f1, t1, f3, t3)
    f1, t1, f2, t2 = _cswap(f1, t1, f2, t2)
    return n0, t0, t1, t2, t3, _F32_ONE - f0, f0 - f1, f1 - f2, f2 - f3, f3


@njit(cache=True, inline="always")
def simplex_params(
    dims: np.ndarray, lo: np.ndarray, inv_step: np.ndarray
) -> tuple[np.float32, np.float32, np.float32, np.float32, np.float32, np.float32, np.float32, np.float32,
           np.float32, np.float32, np.float32, np.float32, np.int32, np.int32, np.int32, np.int32, np.int32,
           np.int32, np.int32]:
    """The grid's parameters as `simplex_corner` takes them: lo (4), inv_step (4), top (4), last (4), strides (3)."""
    s2 = np.int32(dims[3])
    s1 = np.int32(dims[2]) * s2
    s0 = np.int32(dims[1]) * s1
    return (np.float32(lo[0]), np.float32(lo[1]), np.float32(lo[2]), np.float32(lo[3]),
            np.float32(inv_step[0]), np.float32(inv_step[1]), np.float32(inv_step[2]), np.float32(inv_step[3]),
            np.float32(dims[0] - 1), np.float32(dims[1] - 1), np.float32(dims[2] - 1), np.float32(dims[3] - 1),
            np.int32(dims[0] - 2), np.int32(dims[1] - 2), np.int32(dims[2] - 2), np.int32(dims[3] - 2), s0, s1, s2)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def simplex_nodes(
    dims: np.ndarray, lo: np.ndarray, inv_step: np.ndarray, a0: float, a1: float, a2: float, a3: float
) -> tuple[int, int, int, int, int, float, float, float, float, float]:
    """The 5 node indices and barycentric weights of the Kuhn simplex holding the point (see `interp4_simplex`)."""
    n0, t0, t1, t2, t3, w0, w1, w2, w3, w4 = simplex_corner(simplex_params(dims, lo, inv_step), a0, a1, a2, a3)
    n1 = n0 + t0
    n2 = n1 + t1
    n3 = n2 + t2
    return n0, n1, n2, n3, n3 + t3, w0, w1, w2, w3, w4


@njit(cache=True, fastmath=FASTMATH, inline="always")
def interp4_simplex(
    table: np.ndarray, dims: np.ndarray, lo: np.ndarray, inv_step: np.ndarray, a0: float, a1: float, a2: float,
    a3: float,
) -> tuple[float, float, float, float]:
    """Simplex (Kuhn / Freudenthal) interpolation of the same (nodes, 4) table: 5 nodes instead of 16.

    The cell is split into 24 simplices by the order of the fractional coordinates; the value is
    the barycentric blend of the simplex's 5 vertices. Like multilinear interpolation it is exact
    at the nodes, continuous, and second-order accurate, but reads 5 nodes instead of 16: on a
    table larger than the caches that is the difference (it is memory-bound).
    """
    n0, n1, n2, n3, n4, w0, w1, w2, w3, w4 = simplex_nodes(dims, lo, inv_step, a0, a1, a2, a3)
    g0 = np.float32(w0)
    g1 = np.float32(w1)
    g2 = np.float32(w2)
    g3 = np.float32(w3)
    g4 = np.float32(w4)
    c0 = g0 * table[n0, 0] + g1 * table[n1, 0] + g2 * table[n2, 0] + g3 * table[n3, 0] + g4 * table[n4, 0]
    c1 = g0 * table[n0, 1] + g1 * table[n1, 1] + g2 * table[n2, 1] + g3 * table[n3, 1] + g4 * table[n4, 1]
    c2 = g0 * table[n0, 2] + g1 * table[n1, 2] + g2 * table[n2, 2] + g3 * table[n3, 2] + g4 * table[n4, 2]
    c3 = g0 * table[n0, 3] + g1 * table[n1, 3] + g2 * table[n2, 3] + g3 * table[n3, 3] + g4 * table[n4, 3]
    return float(c0), float(c1), float(c2), float(c3)
