"""The softmax temperature that gives the MPPI update a chosen effective sample size.

With the paper's fixed temperature (lambda = 1) the update's effective sample size on the lane tasks is 1.5-3.4 of
1024 samples: one rollout decides each command, and consecutive commands differ by about the noise std (chatter by
construction). Choosing lambda per update so that Kish's effective sample size (sum w)^2 / sum w^2 is a fixed
fraction of the samples averages over that many rollouts instead, whatever the scale of the costs.

The effective sample size grows monotonically with lambda, from the number of samples tied at the lowest cost
(lambda -> 0) to the number of finite-cost samples (lambda -> inf), so a bisection on log lambda finds it.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["temperature_for_effective_samples"]

_BISECTIONS = 24  # log lambda spans ln(1e15) = 34.5: found to 34.5 / 2^24 = 2e-6 relative
_NEGLIGIBLE = 40.0  # exp(-40) = 4e-18: below a float64's resolution next to the lowest cost's weight 1


@njit(cache=True)
def _kish(costs: np.ndarray, c_min: float, inv_t: float) -> float:
    """(sum w)^2 / sum w^2 of w = exp(-(c - c_min) inv_t) over the finite costs, given their minimum c_min."""
    total = 0.0
    total_sq = 0.0
    for c in costs:
        a = (c - c_min) * inv_t
        if a < _NEGLIGIBLE:  # also skips infinite costs; a weight below exp(-40) changes neither sum
            w = np.exp(-a)
            total += w
            total_sq += w * w
    return total * total / total_sq


@njit(cache=True)
def temperature_for_effective_samples(costs: np.ndarray, target: float, fallback: float) -> float:
    """The temperature at which the update's effective sample size is `target` (clipped to what is reachable: at
    least 1, at most the number of finite costs).

    `fallback` is returned when the temperature does not matter: every finite cost is the same (to 1e-12 of their
    size), or none is finite.
    Serial and deterministic: the same costs give the same temperature to the last bit."""
    c_min = np.inf
    c_max = -np.inf
    n_finite = 0
    for c in costs:
        if np.isfinite(c):
            n_finite += 1
            c_min = min(c_min, c)
            c_max = max(c_max, c)
    spread = c_max - c_min
    # equal costs up to rounding (1e-12 of their size): every temperature gives the same update
    if n_finite == 0 or not spread > 1e-12 * max(1.0, abs(c_min)):
        return fallback
    goal = min(max(target, 1.0), float(n_finite))
    lo = np.log(spread * 1e-9)  # every weight but the lowest cost's is below exp(-1e9): ESS = ties at the minimum
    hi = np.log(spread * 1e6)  # every weight is above exp(-1e-6): ESS = n_finite to 1e-6
    for _ in range(_BISECTIONS):
        mid = 0.5 * (lo + hi)
        if _kish(costs, c_min, 1.0 / np.exp(mid)) < goal:  # the minimum found once, not per bisection
            lo = mid
        else:
            hi = mid
    return float(np.exp(hi))
