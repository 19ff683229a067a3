"""Exact GP prediction from the stored Cholesky factors (numba, CPU).

For task t with kernel k(x, x') = s_t exp(-0.5 ||(x - x') / l_t||^2):

    mean(x) = k_*^T alpha_t                       alpha_t = (K_t + noise_t I)^-1 y_t   (O(n))
    var(x)  = s_t - ||L_t^-1 k_*||^2               L_t L_t^T = K_t + noise_t I          (O(n^2))

`var` is the latent (noise-free) variance. `exact_tasks` is the per-point routine the planner's
kernels call; `exact_predict` batches it over points with `prange`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from gpmppi.gp.model_file import GPModel
from gpmppi.kernel_flags import FASTMATH


@njit(cache=True, inline="always", fastmath=FASTMATH)  # fastmath lets the O(n^2) triangular solve use SIMD
def exact_tasks(
    x0: float,
    x1: float,
    x2: float,
    x3: float,
    scaled_x: np.ndarray,
    inv_lengthscale: np.ndarray,
    outputscale: np.ndarray,
    alpha: np.ndarray,
    chol: np.ndarray,
    work: np.ndarray,
    mean: np.ndarray,
    var: np.ndarray,
    with_var: bool,
) -> None:
    """Mean and latent variance of every task at the 4-D point (x0, x1, x2, x3).

    scaled_x (T, n, 4) = train_x / lengthscale per task; work (n,) scratch; mean, var (T,) outputs.
    The one statement of the exact GP: the CUDA kernels compile `exact_tasks.py_func` as a device function.
    """
    n_tasks, n = alpha.shape
    for t in range(n_tasks):
        s = outputscale[t]
        z0 = x0 * inv_lengthscale[t, 0]
        z1 = x1 * inv_lengthscale[t, 1]
        z2 = x2 * inv_lengthscale[t, 2]
        z3 = x3 * inv_lengthscale[t, 3]
        m = 0.0
        for i in range(n):
            d0 = z0 - scaled_x[t, i, 0]
            d1 = z1 - scaled_x[t, i, 1]
            d2 = z2 - scaled_x[t, i, 2]
            d3 = z3 - scaled_x[t, i, 3]
            k = s * math.exp(-0.5 * (d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3))
            work[i] = k
            m += k * alpha[t, i]
        mean[t] = m
        if with_var:
            # forward substitution L v = k_*, accumulating ||v||^2; work is overwritten by v
            q = 0.0
            for i in range(n):
                acc = work[i]
                for j in range(i):
                    acc -= chol[t, i, j] * work[j]
                v = acc / chol[t, i, i]
                work[i] = v
                q += v * v
            var_t = s - q
            var[t] = var_t if var_t > 0.0 else 0.0  # a select: numba's CUDA target cannot compile float max


@njit(cache=True, parallel=True, fastmath=FASTMATH)
def exact_predict_arrays(
    x: np.ndarray,
    scaled_x: np.ndarray,
    inv_lengthscale: np.ndarray,
    outputscale: np.ndarray,
    alpha: np.ndarray,
    chol: np.ndarray,
    with_var: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Batched `exact_tasks` over the rows of x (P, 4): returns mean (P, T), var (P, T)."""
    p_n = x.shape[0]
    n_tasks, n = alpha.shape
    mean = np.zeros((p_n, n_tasks))
    var = np.zeros((p_n, n_tasks))
    for p in prange(p_n):
        work = np.empty(n)
        exact_tasks(x[p, 0], x[p, 1], x[p, 2], x[p, 3], scaled_x, inv_lengthscale, outputscale, alpha, chol, work,
                    mean[p], var[p], with_var)
    return mean, var


class ExactPredictor:
    """Exact GP predictions of a model: `predict(x (P, 4)) -> (mean (P, 2M), latent var (P, 2M))`."""

    def __init__(self, model: GPModel) -> None:
        self.model = model
        self.inv_lengthscale = np.ascontiguousarray(1.0 / model.lengthscale)
        self.scaled_x = np.ascontiguousarray(model.train_x[None, :, :] * self.inv_lengthscale[:, None, :])
        self.outputscale = model.outputscale
        self.alpha = model.alpha
        self.chol = model.chol

    def predict(self, x: np.ndarray, with_var: bool = True) -> tuple[np.ndarray, np.ndarray]:
        x = np.ascontiguousarray(np.atleast_2d(x), dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != 4:
            raise ValueError(f"GP inputs must have shape (P, 4) [v_ref, omega_ref, v, omega], got {x.shape}")
        return exact_predict_arrays(
            x, self.scaled_x, self.inv_lengthscale, self.outputscale, self.alpha, self.chol, with_var
        )
