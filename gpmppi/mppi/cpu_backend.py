"""CPU backend: one numba kernel runs every sample's whole horizon (noise, model, GP, costs) in `prange`.

Each sample draws its noise from the counter-based generator (`rng.normal_pair`), so the result
is identical whatever the thread schedule. Per sample it writes the applied perturbation (the
clipped control minus the nominal one, float32), its total cost, and for the first `xy_out.shape[0]`
samples the XY of the rollout.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from gpmppi.costs import (
    W_COLLISION,
    W_DEVIATION,
    W_EXIT_DISCOUNT,
    W_GOAL,
    W_LANE_EXIT,
    W_SLIP,
    W_SPEED,
    W_TERMINAL,
    W_VARIANCE,
    collision_cost,
    deviation_cost,
    goal_cost,
    lane_exit_cost,
    slip_cost,
    speed_cost,
    variance_cost,
)
from gpmppi.mppi.dynamics import step_state
from gpmppi.mppi.flags import FASTMATH
from gpmppi.mppi.lane import lane_distance_near
from gpmppi.mppi.rng import normal_pair

TASK_LANE = 0
TASK_GOAL = 1


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def rollout_kernel(
    x0: np.ndarray, nominal: np.ndarray, noise_std: np.ndarray, u_lo: np.ndarray, u_hi: np.ndarray, dt: float,
    seed: int, iteration: int,
    dyn_mode: int, theta: np.ndarray, edd5_p: np.ndarray,
    gp_mode: int, table: np.ndarray, dims: np.ndarray, lo: np.ndarray, inv_step: np.ndarray,
    ex_scaled_x: np.ndarray, ex_inv_ls: np.ndarray, ex_outputscale: np.ndarray, ex_alpha: np.ndarray,
    ex_chol: np.ndarray, terrain_w: np.ndarray,
    task_kind: int, seg: np.ndarray, cell_start: np.ndarray, candidates: np.ndarray, field: np.ndarray,
    grid_origin: np.ndarray, inv_cell: float, half_width: float, tightened_hw: np.ndarray, speed_target: float,
    goal: np.ndarray, obstacles: np.ndarray, radii: np.ndarray, cost_w: np.ndarray,
    eps_out: np.ndarray, cost_out: np.ndarray, xy_out: np.ndarray,
) -> None:
    samples = eps_out.shape[0]
    horizon = nominal.shape[0]
    n_xy = xy_out.shape[0]
    n_tasks = ex_alpha.shape[0]
    n_train = ex_alpha.shape[1]
    discount = cost_w[W_EXIT_DISCOUNT]
    for s in prange(samples):
        work = np.empty(n_train)
        gp_in = np.empty(4)
        gp_mean = np.empty(n_tasks)
        gp_var = np.empty(n_tasks)
        px = x0[0]
        py = x0[1]
        yaw = x0[2]
        v = x0[3]
        w = x0[4]
        if s < n_xy:
            xy_out[s, 0, 0] = px
            xy_out[s, 0, 1] = py
        total = 0.0
        discount_k = 1.0
        base = (iteration * samples + s) * horizon
        for k in range(horizon):
            z0, z1 = normal_pair(seed, base + k)
            u0 = nominal[k, 0] + noise_std[0] * z0
            u1 = nominal[k, 1] + noise_std[1] * z1
            u0 = min(max(u0, u_lo[0]), u_hi[0])
            u1 = min(max(u1, u_lo[1]), u_hi[1])
            eps_out[s, k, 0] = u0 - nominal[k, 0]
            eps_out[s, k, 1] = u1 - nominal[k, 1]
            px, py, yaw, v, w, cv, cw = step_state(
                dyn_mode, dt, theta, edd5_p, gp_mode, table, dims, lo, inv_step, ex_scaled_x, ex_inv_ls,
                ex_outputscale, ex_alpha, ex_chol, terrain_w, work, gp_in, gp_mean, gp_var,
                px, py, yaw, v, w, u0, u1,
            )
            if s < n_xy:
                xy_out[s, k + 1, 0] = px
                xy_out[s, k + 1, 1] = py
            c = variance_cost(cv, cw, cost_w[W_VARIANCE])
            if task_kind == TASK_LANE:
                d = lane_distance_near(
                    seg, cell_start, candidates, field, grid_origin, inv_cell, px, py, tightened_hw[k + 1]
                )
                c += deviation_cost(d, half_width, cost_w[W_DEVIATION])
                c += slip_cost(v, w, u0, u1, cost_w[W_SLIP])
                c += lane_exit_cost(d, tightened_hw[k + 1], discount_k, cost_w[W_LANE_EXIT])
                c += speed_cost(v, speed_target, cost_w[W_SPEED])
            else:
                c += collision_cost(px, py, obstacles, radii[k + 1], cost_w[W_COLLISION])
                c += goal_cost(px, py, goal, cost_w[W_GOAL])
            total += c
            discount_k *= discount
        if task_kind == TASK_GOAL:
            total += goal_cost(px, py, goal, cost_w[W_TERMINAL])
        if not np.isfinite(total):
            total = np.inf
        cost_out[s] = total


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
