"""The exact and grid GP predictors as numba.cuda device functions, compiled from the CPU functions' source.

Planner kernels call `gp_exact_device` / `gp_grid_device` per sample and step, inside one launch.
`gp_exact_device` needs a per-thread scratch row of length n (the number of training inputs): pass
a row of a device array of shape (threads, n). `cuda_predict` runs either predictor over many
points (used by tests under the CUDA simulator, and by benchmarks on a GPU).
"""

from __future__ import annotations

import types
from collections.abc import Callable

import numpy as np
from numba import cuda
from numba.core.registry import CPUDispatcher

from gpmppi.gp.exact import exact_tasks
from gpmppi.gp.grid_interp import grid_interp_point
from gpmppi.gp.model_file import GPModel


def device_function(py_func: Callable, **callees: Callable) -> Callable:
    """`py_func` (the plain Python of a CPU `njit` function) compiled as an inlined CUDA device function.

    The CPU and CUDA code then state each equation once. `callees` rebinds global names the function
    calls (CPU `njit` dispatchers) to their device versions: numba resolves a function's globals
    through `__globals__`, so a copy of the function with an updated globals dict calls the device
    versions when compiled for CUDA, while the CPU original keeps calling the CPU ones.
    """
    if callees:
        missing = sorted(set(callees) - set(py_func.__code__.co_names))
        if missing:
            raise ValueError(f"{py_func.__qualname__} calls no global named {missing}")
        scope = dict(py_func.__globals__)
        scope.update(callees)
        py_func = types.FunctionType(py_func.__code__, scope, py_func.__name__, py_func.__defaults__,
                                     py_func.__closure__)
    return cuda.jit(device=True, inline=True)(py_func)


_DEVICE_VERSIONS: dict[int, Callable] = {}


def set_device_version(func: CPUDispatcher, device_func: Callable) -> None:
    """Make `device_func` the device twin of `func`, for the few primitives numba's CUDA target compiles
    differently (call before building twins of the functions that use `func`)."""
    _DEVICE_VERSIONS[id(func)] = device_func


def device_version(func: CPUDispatcher) -> Callable:
    """The CUDA device twin of a CPU `njit` function: its Python compiled by `device_function`, every `njit`
    function it calls replaced by that function's twin (recursively; one twin per function)."""
    found = _DEVICE_VERSIONS.get(id(func))
    if found is None:
        py_func = func.py_func
        scope = py_func.__globals__
        callees = {name: device_version(scope[name]) for name in py_func.__code__.co_names
                   if isinstance(scope.get(name), CPUDispatcher)}
        found = device_function(py_func, **callees)
        _DEVICE_VERSIONS[id(func)] = found
    return found


gp_exact_device = device_version(exact_tasks)
gp_grid_device = device_version(grid_interp_point)


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
