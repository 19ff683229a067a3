"""The CPU's serial kernels of a plan beside the rollouts: the nominal sequence's critic costs and the MPPI update
(`backends` calls them for either backend)."""

from __future__ import annotations

import numpy as np
from numba import njit

from gpmppi.kernel_flags import FASTMATH
from gpmppi.mppi.bundles import CRITICS
from gpmppi.mppi.costs import advance_state, stage_critics, start_state, terminal_critics, weight_vector
from gpmppi.mppi.dynamics import gp_scratch, velocity_coefficients
from gpmppi.mppi.step import sample_step, step_inputs

__all__ = ["nominal_critic_costs", "softmax_update"]


@njit(cache=True, fastmath=FASTMATH)
def nominal_critic_costs(model: tuple, task: tuple, sampling: tuple, cost: tuple) -> np.ndarray:
    """Each critic's cost (`CRITICS` order) of the sampling bundle's nominal sequence, clipped to its limits (its first
    command to the rate limits too) as the kernels clip a sampled command.

    Serial, one rollout by the kernels' own step (`step.sample_step`) with zero noise, so that the nominal is
    clipped exactly as a sample is, compiled with the kernels' flags (without them the float32 table reads and the
    pose step round differently and the sum strayed 5e-9 from the kernel's cost): the kernels add the critics of a
    step into one cost, this keeps them apart; their sum is the kernels' cost.
    """
    tightened_hw = task.tightened_hw
    radii = task.radii
    horizon = sampling.nominal.shape[0]
    # the sampling bundle's own limits, but no noise: whatever its noise std, the sequence scored is the nominal
    inputs = step_inputs(model, sampling, np.zeros(2), 0.0, velocity_coefficients(model.theta, model.lateral))
    dt = sampling.dt
    scratch = gp_scratch(model)
    cost_w = weight_vector(cost)
    x0 = sampling.x0
    s = (x0[0], x0[1], x0[2], x0[3], x0[4])
    d = (0.0, 0.0)
    out = np.zeros(len(CRITICS))
    state = start_state(cost_w)
    for k in range(horizon):
        u, d, s, variances = sample_step(sampling.seed, k, k, inputs, scratch, dt, s, d)
        stage_critics(cost_w, task, tightened_hw[k + 1], radii[k + 1], state, s, u, variances, out)
        state = advance_state(state, cost_w)
    terminal_critics(cost_w, task, tightened_hw[horizon], radii[horizon], state, s, out)
    return out


@njit(cache=True)
def softmax_update(
    nominal: np.ndarray, eps: np.ndarray, costs: np.ndarray, temperature: float
) -> tuple[np.ndarray, np.ndarray]:
    """MPPI update: weights exp(-(c - c_min) / lambda) normalised; nominal + sum_s w_s eps_s.

    Serial so the sum is bit-for-bit reproducible. Samples with infinite cost get zero weight; if
    every cost is infinite the nominal sequence is kept.
    """
    samples = costs.shape[0]
    c_min = np.inf
    for s in range(samples):
        if costs[s] < c_min:
            c_min = costs[s]
    weights = np.zeros(samples)
    if not np.isfinite(c_min):
        return nominal.copy(), weights
    total = 0.0
    for s in range(samples):
        if np.isfinite(costs[s]):
            weights[s] = np.exp(-(costs[s] - c_min) / temperature)
            total += weights[s]
    out = nominal.copy()
    for s in range(samples):
        ws = weights[s] / total
        weights[s] = ws
        if ws > 0.0:
            for k in range(nominal.shape[0]):
                out[k, 0] += ws * eps[s, k, 0]
                out[k, 1] += ws * eps[s, k, 1]
    return out, weights
