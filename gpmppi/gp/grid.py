"""The grid GP predictor: exact predictions tabulated on a regular 4-D grid, then interpolated.

The table (`grid_table`) spans the model's domain box, with nodes per axis sized from the model's
lengthscales; between nodes the predictor interpolates multilinearly (16 nodes) or, as the planner
does by default, in the point's Kuhn simplex (5 nodes); outside the box it clamps (the GP is not
trusted outside its training domain).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numba import njit, prange

from gpmppi.gp.grid_interp import grid_interp, simplex_interp_point
from gpmppi.gp.grid_table import (
    DEFAULT_SPACING,
    GridTable,
    build_grid,
    grid_axes,
    grid_dims,
    model_grid_dims,
    predict_dense,
)
from gpmppi.gp.model_file import GPModel

__all__ = [
    "DEFAULT_NODES", "DEFAULT_SPACING", "GridPredictor", "GridTable", "build_grid", "grid_axes", "grid_dims",
    "model_grid_dims", "predict_dense",
]

DEFAULT_NODES = 30  # uniform nodes per axis of synthetic benchmark models (real models are sized by `grid_dims`)

Interpolation = Literal["multilinear", "simplex"]


@njit(cache=True, parallel=True)
def _grid_predict_arrays(table: np.ndarray, lo: np.ndarray, inv_step: np.ndarray, x: np.ndarray) -> np.ndarray:
    out = np.empty((x.shape[0], table.shape[4]))
    for p in prange(x.shape[0]):
        grid_interp(table, lo, inv_step, x[p], out[p])
    return out


@njit(cache=True, parallel=True)
def _simplex_predict_arrays(table: np.ndarray, lo: np.ndarray, inv_step: np.ndarray, x: np.ndarray) -> np.ndarray:
    out = np.empty((x.shape[0], table.shape[4]))
    for p in prange(x.shape[0]):
        simplex_interp_point(table, lo, inv_step, x[p, 0], x[p, 1], x[p, 2], x[p, 3], out[p])
    return out


class GridPredictor:
    """Grid predictions of a model: `predict(x (P, 4)) -> (mean (P, 2M), latent var (P, 2M))`.

    `interpolation`: "multilinear" (16 nodes) or "simplex" (the planner's default, 5 nodes).
    """

    def __init__(self, model: GPModel, interpolation: Interpolation = "multilinear") -> None:
        if interpolation not in ("multilinear", "simplex"):
            raise ValueError(f"interpolation must be 'multilinear' or 'simplex', got {interpolation!r}")
        self.model = model
        self.interpolation = interpolation
        g = model.grid()
        # the table may be stored as float32; interpolate in float64 like the planner kernels do
        self.table = np.ascontiguousarray(g.table, dtype=np.float64)
        self.lo = np.ascontiguousarray(g.lo, dtype=np.float64)
        self.inv_step = np.ascontiguousarray(g.inv_step, dtype=np.float64)

    def predict(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.ascontiguousarray(np.atleast_2d(x), dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != 4:
            raise ValueError(f"GP inputs must have shape (P, 4) [v_ref, omega_ref, v, omega], got {x.shape}")
        fn = _simplex_predict_arrays if self.interpolation == "simplex" else _grid_predict_arrays
        out = fn(self.table, self.lo, self.inv_step, x)
        t = self.model.n_tasks
        return out[:, :t], out[:, t:]
