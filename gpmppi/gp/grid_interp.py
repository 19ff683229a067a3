"""Multilinear interpolation in a regular 4-D table (the `grid` GP predictor's hot path).

A table has shape (G0, G1, G2, G3, K): K channels at every node of a regular grid with
lower corner `lo` and spacing `step` over the GP input `[v_ref, omega_ref, v, omega]`.
Inputs outside the grid are clamped to its faces (the GP is not trusted outside its
training domain anyway).

Each function here is the single statement of its math: the CPU uses it as compiled by
`numba.njit`, the CUDA kernels compile its `.py_func` as a device function
(`gpmppi.gp.cuda_kernels.device_function`).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def grid_cell(x: float, lo: float, inv_step: float, g: int) -> tuple[int, float]:
    """Cell index and fraction of `x` along one axis of `g` nodes, clamped to the faces.

    Written as selects, not branches: rollouts clip many commands to the limits, which are the grid's
    faces, so a branch on "outside the grid" would be mispredicted often.
    """
    t = (x - lo) * inv_step
    t = 0.0 if t < 0.0 else t
    top = g - 1.0
    t = top if t > top else t
    i = int(t)
    i = g - 2 if i > g - 2 else i
    return i, t - i


@njit(cache=True, inline="always")
def grid_interp_point(
    table: np.ndarray, lo: np.ndarray, inv_step: np.ndarray, x0: float, x1: float, x2: float, x3: float,
    out: np.ndarray,
) -> None:
    """Write the K interpolated channels at (x0, x1, x2, x3) into `out` (length K)."""
    i0, f0 = grid_cell(x0, lo[0], inv_step[0], table.shape[0])
    i1, f1 = grid_cell(x1, lo[1], inv_step[1], table.shape[1])
    i2, f2 = grid_cell(x2, lo[2], inv_step[2], table.shape[2])
    i3, f3 = grid_cell(x3, lo[3], inv_step[3], table.shape[3])
    k_n = table.shape[4]
    for k in range(k_n):
        out[k] = 0.0
    for c in range(16):
        b0 = c & 1
        b1 = (c >> 1) & 1
        b2 = (c >> 2) & 1
        b3 = (c >> 3) & 1
        w = (f0 if b0 else 1.0 - f0) * (f1 if b1 else 1.0 - f1)
        w *= (f2 if b2 else 1.0 - f2) * (f3 if b3 else 1.0 - f3)
        for k in range(k_n):
            out[k] += w * table[i0 + b0, i1 + b1, i2 + b2, i3 + b3, k]


@njit(cache=True)
def grid_interp(
    table: np.ndarray, lo: np.ndarray, inv_step: np.ndarray, x: np.ndarray, out: np.ndarray
) -> None:
    """Write the K interpolated channels at the 4-D point `x` into `out` (length K)."""
    grid_interp_point(table, lo, inv_step, x[0], x[1], x[2], x[3], out)


@njit(cache=True, inline="always")
def simplex_interp_point(
    table: np.ndarray, lo: np.ndarray, inv_step: np.ndarray, x0: float, x1: float, x2: float, x3: float,
    out: np.ndarray,
) -> None:
    """Write the K channels at (x0, x1, x2, x3) interpolated in the point's Kuhn simplex into `out`.

    The same interpolation as the planner's `interp4_simplex` (5 nodes instead of 16), in double
    precision and for any number of channels: the cell is split by the order of the fractional
    coordinates; the vertices are the cell's first node, then one more axis stepped at a time in
    that order, and the weights are the differences of the sorted fractions.
    """
    idx = np.empty(4, dtype=np.int64)
    frac = np.empty(4)
    idx[0], frac[0] = grid_cell(x0, lo[0], inv_step[0], table.shape[0])
    idx[1], frac[1] = grid_cell(x1, lo[1], inv_step[1], table.shape[1])
    idx[2], frac[2] = grid_cell(x2, lo[2], inv_step[2], table.shape[2])
    idx[3], frac[3] = grid_cell(x3, lo[3], inv_step[3], table.shape[3])
    order = np.argsort(-frac, kind="mergesort")
    k_n = table.shape[4]
    prev = 1.0
    for v in range(5):
        f = frac[order[v]] if v < 4 else 0.0
        w = prev - f
        for k in range(k_n):
            val = w * table[idx[0], idx[1], idx[2], idx[3], k]
            out[k] = val if v == 0 else out[k] + val
        if v < 4:
            idx[order[v]] += 1
            prev = f
