"""Multilinear interpolation in a regular 4-D table (the `grid` GP predictor's hot path).

A table has shape (G0, G1, G2, G3, K): K channels at every node of a regular grid with
lower corner `lo` and spacing `step` over the GP input `[v_ref, omega_ref, v, omega]`.
Inputs outside the grid are clamped to its faces (the GP is not trusted outside its
training domain anyway).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _cell(x: float, lo: float, inv_step: float, g: int) -> tuple[int, float]:
    t = (x - lo) * inv_step
    if t <= 0.0:
        return 0, 0.0
    if t >= g - 1:
        return g - 2, 1.0
    i = int(t)
    return i, t - i


@njit(cache=True)
def grid_interp(
    table: np.ndarray, lo: np.ndarray, inv_step: np.ndarray, x: np.ndarray, out: np.ndarray
) -> None:
    """Write the K interpolated channels at the 4-D point `x` into `out` (length K)."""
    i0, f0 = _cell(x[0], lo[0], inv_step[0], table.shape[0])
    i1, f1 = _cell(x[1], lo[1], inv_step[1], table.shape[1])
    i2, f2 = _cell(x[2], lo[2], inv_step[2], table.shape[2])
    i3, f3 = _cell(x[3], lo[3], inv_step[3], table.shape[3])
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
        node = table[i0 + b0, i1 + b1, i2 + b2, i3 + b3]
        for k in range(k_n):
            out[k] += w * node[k]
