"""Compiler flags and scalar primitives shared by the planner kernels."""

from __future__ import annotations

from numba import njit

# fastmath without 'nnan'/'ninf': the kernels rely on inf/NaN checks (infinite costs, safe controls)
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(cache=True, inline="always")
def fmax(a: float, b: float) -> float:
    """max of two floats: a branch-free maxsd on the CPU (the kernels' data-dependent choices would
    mispredict as branches). numba's CUDA target cannot compile float `max`: its device twin is a
    select (`gpmppi.mppi.cuda_backend`)."""
    return max(a, b)


@njit(cache=True, inline="always")
def fmin(a: float, b: float) -> float:
    """min of two floats (see `fmax`)."""
    return min(a, b)
