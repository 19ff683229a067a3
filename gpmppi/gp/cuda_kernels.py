"""The exact and grid GP predictors as numba.cuda device functions (same math as the CPU versions).

Planner kernels call `gp_exact_device` / `gp_grid_device` per sample and step, inside one launch.
`gp_exact_device` needs a per-thread scratch row of length n (the number of training inputs): pass
a row of a device array of shape (threads, n). `cuda_predict` runs either predictor over many
points (used by tests under the CUDA simulator, and by benchmarks on a GPU).
"""

from __future__ import annotations

import math

import numpy as np
from numba import cuda

from gpmppi.gp.model_file import GPModel


@cuda.jit(device=True, cache=True)
def gp_exact_device(x0, x1, x2, x3, scaled_x, inv_lengthscale, outputscale, alpha, chol, work, mean, var, with_var):
    """Mean and latent variance of every task at (x0..x3); see `exact.exact_point`."""
    n_tasks = alpha.shape[0]
    n = alpha.shape[1]
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
            q = 0.0
            for i in range(n):
                acc = work[i]
                for j in range(i):
                    acc -= chol[t, i, j] * work[j]
                v = acc / chol[t, i, i]
                work[i] = v
                q += v * v
            var[t] = max(s - q, 0.0)


@cuda.jit(device=True, cache=True)
def _cell(x, lo, inv_step, g):
    t = (x - lo) * inv_step
    if t <= 0.0:
        return 0, 0.0
    if t >= g - 1:
        return g - 2, 1.0
    i = int(t)
    return i, t - i


@cuda.jit(device=True, cache=True)
def gp_grid_device(table, lo, inv_step, x0, x1, x2, x3, out):
    """Multilinear interpolation of all channels at (x0..x3), clamped; see `grid_interp.grid_interp`."""
    i0, f0 = _cell(x0, lo[0], inv_step[0], table.shape[0])
    i1, f1 = _cell(x1, lo[1], inv_step[1], table.shape[1])
    i2, f2 = _cell(x2, lo[2], inv_step[2], table.shape[2])
    i3, f3 = _cell(x3, lo[3], inv_step[3], table.shape[3])
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


@cuda.jit(cache=True)
def _exact_kernel(x, scaled_x, inv_lengthscale, outputscale, alpha, chol, work, mean, var):
    p = cuda.grid(1)
    if p < x.shape[0]:
        gp_exact_device(x[p, 0], x[p, 1], x[p, 2], x[p, 3], scaled_x, inv_lengthscale, outputscale, alpha, chol,
                        work[p], mean[p], var[p], True)


@cuda.jit(cache=True)
def _grid_kernel(x, table, lo, inv_step, out):
    p = cuda.grid(1)
    if p < x.shape[0]:
        gp_grid_device(table, lo, inv_step, x[p, 0], x[p, 1], x[p, 2], x[p, 3], out[p])


def cuda_predict(
    model: GPModel, x: np.ndarray, mode: str = "exact", threads: int = 64
) -> tuple[np.ndarray, np.ndarray]:
    """(mean, latent var) of shape (P, 2M) computed by the device functions, one thread per point."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    p_n, n_tasks = x.shape[0], model.n_tasks
    blocks = (p_n + threads - 1) // threads
    d_x = cuda.to_device(x)
    if mode == "exact":
        inv_ls = np.ascontiguousarray(1.0 / model.lengthscale)
        scaled = np.ascontiguousarray(model.train_x[None] * inv_ls[:, None, :])
        d_mean = cuda.device_array((p_n, n_tasks))
        d_var = cuda.device_array((p_n, n_tasks))
        d_work = cuda.device_array((p_n, model.train_x.shape[0]))
        _exact_kernel[blocks, threads](
            d_x, cuda.to_device(scaled), cuda.to_device(inv_ls), cuda.to_device(model.outputscale),
            cuda.to_device(model.alpha), cuda.to_device(model.chol), d_work, d_mean, d_var,
        )
        return d_mean.copy_to_host(), d_var.copy_to_host()
    if mode == "grid":
        g = model.grid()
        d_out = cuda.device_array((p_n, 2 * n_tasks))
        _grid_kernel[blocks, threads](
            d_x, cuda.to_device(np.ascontiguousarray(g.table, dtype=np.float64)), cuda.to_device(g.lo),
            cuda.to_device(g.inv_step), d_out,
        )
        out = d_out.copy_to_host()
        return out[:, :n_tasks], out[:, n_tasks:]
    raise ValueError(f"mode must be 'exact' or 'grid', got {mode!r}")
