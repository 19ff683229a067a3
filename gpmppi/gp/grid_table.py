"""The grid predictor's table: exact GP predictions tabulated on a regular 4-D grid, and its sizing.

The table spans the model's domain box with G_d nodes along axis d; each node holds the 2M means
and the 2M latent variances. The node counts follow the model: along each axis the spacing is at
most `spacing` times the smallest lengthscale any task has on that axis (`grid_dims`), because the
interpolation error of an RBF-kernel GP grows with (spacing / lengthscale)^2 (second order, for
both the multilinear and the simplex interpolation).

This module needs only the model's arrays (`ExactGP`), not the model file, so the file format
(`model_file`) can build a table on first use without a two-way import.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

# Node spacing along an axis as a fraction of the smallest lengthscale on it. The worst task's RMS
# mean error of the planner's simplex interpolation falls as spacing^2: measured (`gpmppi bench gp
# --spacing`, docs/benchmarks.md) 0.75% / 0.50% at 0.16 / 0.13 on the shipped model and 1.03% / 0.67%
# on the paper's; 0.14 keeps both near 0.8% or below, under the 1% goal.
DEFAULT_SPACING = 0.14
MIN_NODES = 2


class ExactGP(Protocol):
    """What tabulating needs of a model: the exact GP's arrays (`model_file.GPModel` has them)."""

    domain_lo: np.ndarray  # (4,) lower corner of the input box
    domain_hi: np.ndarray  # (4,) upper corner of the input box
    train_x: np.ndarray  # (n, 4) shared training inputs
    lengthscale: np.ndarray  # (2M, 4) ARD lengthscales per task, input units
    outputscale: np.ndarray  # (2M,) kernel output scale per task
    alpha: np.ndarray  # (2M, n) (K + noise I)^-1 y per task
    chol: np.ndarray  # (2M, n, n) lower Cholesky factor of K + noise I per task


@dataclass
class GridTable:
    """Precomputed GP predictions on a regular 4-D grid, for `grid_interp`.

    `table` has shape (G0, G1, G2, G3, 4M): the means of the 2M tasks, then their latent variances.
    """

    table: np.ndarray
    lo: np.ndarray
    inv_step: np.ndarray

    @property
    def dims(self) -> tuple[int, int, int, int]:
        """Nodes along each input axis [v_ref, omega_ref, v, omega]."""
        g0, g1, g2, g3 = (int(n) for n in self.table.shape[:4])
        return g0, g1, g2, g3

    @property
    def nodes(self) -> int:
        """The largest node count of the four axes (the count of a uniform grid)."""
        return max(self.dims)

    @property
    def n_nodes(self) -> int:
        """Total number of grid nodes."""
        return math.prod(self.dims)

    @property
    def hi(self) -> np.ndarray:
        return self.lo + (np.asarray(self.table.shape[:4]) - 1) / self.inv_step


def grid_dims(
    lengthscale: np.ndarray, lo: np.ndarray, hi: np.ndarray, spacing: float = DEFAULT_SPACING
) -> tuple[int, int, int, int]:
    """Nodes per axis so the spacing along each axis is <= `spacing` x that axis's smallest lengthscale.

    nodes_d = ceil((hi_d - lo_d) / (spacing * min_t lengthscale[t, d])) + 1, at least 2.
    """
    if not (np.isfinite(spacing) and spacing > 0):
        raise ValueError(f"grid spacing must be a positive fraction of the lengthscale, got {spacing}")
    ls = np.asarray(lengthscale, dtype=np.float64)
    span = np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)
    if ls.ndim != 2 or ls.shape[1] != 4 or span.shape != (4,):
        raise ValueError(f"lengthscale must be (tasks, 4) and the box 4-D, got {ls.shape} and {span.shape}")
    # a tiny tolerance so that an exact multiple does not get an extra node from rounding
    cells = np.ceil(span / (spacing * ls.min(axis=0)) - 1e-9)
    g0, g1, g2, g3 = (max(MIN_NODES, int(c) + 1) for c in cells)
    return g0, g1, g2, g3


def model_grid_dims(model: ExactGP, spacing: float = DEFAULT_SPACING) -> tuple[int, int, int, int]:
    """`grid_dims` over the model's domain box and lengthscales."""
    return grid_dims(model.lengthscale, model.domain_lo, model.domain_hi, spacing)


def predict_dense(model: ExactGP, x: np.ndarray, chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    """Exact mean and latent variance (P, 2M) with BLAS triangular solves (fast for many points).

    Same math as `exact.exact_tasks`; used to fill grid tables and for large offline batches.
    """
    # here, not at the top: scipy.linalg is ~0.15 s of every process that loads a model, and a stored table needs none
    from scipy.linalg import solve_triangular

    x = np.ascontiguousarray(np.atleast_2d(x), dtype=np.float64)
    n_tasks = model.lengthscale.shape[0]
    mean = np.empty((x.shape[0], n_tasks))
    var = np.empty((x.shape[0], n_tasks))
    for start in range(0, x.shape[0], chunk):
        xc = x[start : start + chunk]
        for t in range(n_tasks):
            a = xc / model.lengthscale[t]
            b = model.train_x / model.lengthscale[t]
            sq = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
            k_star = model.outputscale[t] * np.exp(-0.5 * np.maximum(sq, 0.0))  # (c, n)
            mean[start : start + chunk, t] = k_star @ model.alpha[t]
            v = solve_triangular(model.chol[t], k_star.T, lower=True, check_finite=False)
            var[start : start + chunk, t] = np.maximum(model.outputscale[t] - (v * v).sum(0), 0.0)
    return mean, var


def grid_axes(lo: np.ndarray, hi: np.ndarray, dims: int | tuple[int, ...]) -> list[np.ndarray]:
    """Node coordinates along each axis (`dims`: one count for every axis, or four)."""
    counts = (dims,) * 4 if isinstance(dims, (int, np.integer)) else tuple(dims)
    return [np.linspace(lo[d], hi[d], int(counts[d])) for d in range(4)]


def build_grid(
    model: ExactGP, nodes: int | tuple[int, int, int, int] | None = None, spacing: float = DEFAULT_SPACING
) -> GridTable:
    """Tabulate the exact GP over the model's domain box.

    `nodes`: one count for every axis, or four; None (the default) sizes each axis from the model's
    lengthscales (`model_grid_dims` with `spacing`).
    """
    if nodes is None:
        dims = model_grid_dims(model, spacing)
    elif isinstance(nodes, (int, np.integer)):
        dims = (int(nodes),) * 4
    else:
        dims = tuple(int(n) for n in nodes)
    if len(dims) != 4 or min(dims) < MIN_NODES:
        raise ValueError(f"a grid needs 4 axes of at least {MIN_NODES} nodes each, got {dims}")
    lo, hi = np.asarray(model.domain_lo, dtype=np.float64), np.asarray(model.domain_hi, dtype=np.float64)
    axes = grid_axes(lo, hi, dims)
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 4)
    mean, var = predict_dense(model, pts)
    n_tasks = mean.shape[1]
    table = np.concatenate([mean, var], axis=1).reshape(*dims, 2 * n_tasks)
    inv_step = (np.asarray(dims) - 1) / (hi - lo)
    return GridTable(table=np.ascontiguousarray(table), lo=lo.copy(), inv_step=inv_step)


# ---- the table as the model file stores it ----------------------------------------------------------------------
def encode_grid_table(table: np.ndarray) -> dict[str, np.ndarray]:
    """16-bit per-channel quantization, then wrapping (mod 2^16) differences along the 4 grid axes."""
    table = np.asarray(table, dtype=np.float64)
    offset = table.min(axis=(0, 1, 2, 3))
    span = table.max(axis=(0, 1, 2, 3)) - offset
    scale = np.where(span > 0, span / 65535.0, 1.0)
    q = np.round((table - offset) / scale).astype(np.uint16)
    for axis in range(4):
        q = np.diff(q, axis=axis, prepend=np.zeros_like(q.take([0], axis=axis)))
    return {"grid_q": q, "grid_offset": offset, "grid_scale": scale}


def decode_grid_table(q: np.ndarray, offset: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Inverse of `encode_grid_table` (exact on the quantized values)."""
    q = np.asarray(q)
    if q.dtype != np.uint16 or q.ndim != 5:
        raise ValueError(f"grid_q must be a 5-D uint16 array, got {q.dtype} {q.shape}")
    offset = np.asarray(offset, dtype=np.float64)
    scale = np.asarray(scale, dtype=np.float64)
    if offset.shape != (q.shape[4],) or scale.shape != (q.shape[4],):
        raise ValueError(f"grid_offset/grid_scale shapes {offset.shape}/{scale.shape} do not match grid_q {q.shape}")
    # in place, slab by slab (the same wrapping uint16 sums as cumsum along each axis): cumsum's new array per axis
    # and `offset + scale * q`'s two float64 temporaries cost a fresh process that loads the shipped profile 0.3-0.9 s
    # of CPU, most of it system time faulting in fresh memory (0.04 s in place)
    q = np.array(q, dtype=np.uint16, order="C")
    for axis in range(4):
        slabs = np.moveaxis(q, axis, 0)
        for i in range(1, slabs.shape[0]):
            np.add(slabs[i], slabs[i - 1], out=slabs[i])
    table = q.astype(np.float64)
    table *= scale
    table += offset
    return table
