"""CPU backend: one numba kernel runs every sample's whole horizon (noise, model, GP, costs) in `prange`.

Threads take groups of `GROUP` samples and step them in lockstep over the horizon.

The kernel takes the five bundles of `gpmppi.mppi.bundles` (their `.args()` tuples).

Each sample draws its noise from the counter-based generator (`rng.normal_pair`), so the result
is identical whatever the thread schedule. Per sample it writes the applied perturbation (the
clipped control minus the nominal one, float32), its total cost, and for the first `xy_out.shape[0]`
samples the XY of the rollout.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from gpmppi.kernel_flags import FASTMATH, prefetch_row
from gpmppi.mppi.bundles import (
    CRITICS,
    K_EXIT_DISCOUNT,
    K_TERMINAL,
    M_DIMS,
    M_DYN_MODE,
    M_EDD5,
    M_EX_ALPHA,
    M_EX_CHOL,
    M_EX_INV_LS,
    M_EX_OUTPUTSCALE,
    M_EX_SCALED_X,
    M_GP_MODE,
    M_INV_STEP,
    M_LATERAL,
    M_LO,
    M_TABLE,
    M_TERRAIN_W,
    M_THETA,
    O_COST,
    O_EPS,
    O_XY,
    S_DT,
    S_ITERATION,
    S_NOISE_STD,
    S_NOMINAL,
    S_SEED,
    S_U_HI,
    S_U_LO,
    S_X0,
    T_CANDIDATES,
    T_CELL_START,
    T_FIELD,
    T_GOAL,
    T_HALF_WIDTH,
    T_INV_CELL,
    T_KIND,
    T_OBSTACLES,
    T_ORIGIN,
    T_RADII,
    T_SEG,
    T_SPEED_TARGET,
    T_TIGHTENED_HW,
    TASK_GOAL,
)
from gpmppi.mppi.costs import goal_term, stage_cost, stage_critics, weight_vector
from gpmppi.mppi.dynamics import (
    DYN_GP,
    GP_SIMPLEX,
    advance,
    gp_inputs,
    gp_residual,
    gp_scratch,
    step_state,
    velocity_coefficients,
)
from gpmppi.mppi.gp_table import simplex_corner, simplex_params
from gpmppi.mppi.rng import clip, noisy_command

__all__ = ["GROUP", "nominal_critic_costs", "rollout_kernel", "softmax_update"]

# samples a thread steps in lockstep: each sample's step waits on its own GP table reads (the next
# state needs them), so interleaving independent samples lets those memory reads overlap
GROUP = 32


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _draw_commands(
    seed: int, counter0: int, horizon: int, k: int, limits: tuple, first: int, n_in: int, eps_out: np.ndarray,
    cmd: np.ndarray,
) -> None:
    """Step k's noisy commands of the group's samples first .. first + n_in - 1 into `cmd`; perturbations to eps_out.

    `counter0` = iteration * samples (the noise counter of sample s, step k is (counter0 + s) * horizon + k);
    `limits` = (nominal, noise_std, u_lo, u_hi)."""
    nominal, noise_std, u_lo, u_hi = limits
    for j in range(n_in):
        s = first + j
        u0, u1 = noisy_command(seed, (counter0 + s) * horizon + k, nominal, k, noise_std, u_lo, u_hi)
        eps_out[s, k, 0] = u0 - nominal[k, 0]
        eps_out[s, k, 1] = u1 - nominal[k, 1]
        cmd[j, 0] = u0
        cmd[j, 1] = u1


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _add_costs(
    n_in: int, st: np.ndarray, cmd: np.ndarray, res: np.ndarray, total: np.ndarray, kind: int, cost_w: np.ndarray,
    geo: tuple, bounds: tuple, discount_k: float,
) -> None:
    """Add one step's stage cost to each sample's total: states `st` after the step, its commands and GP variances;
    `bounds` = (this step's tightened half-width, its inflated radii)."""
    tightened_hw, radii = bounds
    for j in range(n_in):
        total[j] += stage_cost(kind, cost_w, geo, tightened_hw, radii, discount_k,
                               (st[j, 0], st[j, 1], st[j, 2], st[j, 3], st[j, 4]), (cmd[j, 0], cmd[j, 1]),
                               (res[j, 2], res[j, 3]))


@njit(parallel=True, cache=True, fastmath=FASTMATH)
def rollout_kernel(model: tuple, task: tuple, sampling: tuple, cost: tuple, out: tuple) -> None:
    """Every sample's rollout and total cost; the bundles' tuples (`gpmppi.mppi.bundles`, `.args()`)."""
    # every field is read here, once, outside the sample loops: read from the tuples inside them the kernel ran
    # slower and its results differed in the last bits
    dyn_mode = model[M_DYN_MODE]
    theta = model[M_THETA]
    lateral = model[M_LATERAL]
    edd5_p = model[M_EDD5]
    gp_mode = model[M_GP_MODE]
    table = model[M_TABLE]
    dims = model[M_DIMS]
    lo = model[M_LO]
    inv_step = model[M_INV_STEP]
    ex_scaled_x = model[M_EX_SCALED_X]
    ex_inv_ls = model[M_EX_INV_LS]
    ex_outputscale = model[M_EX_OUTPUTSCALE]
    ex_alpha = model[M_EX_ALPHA]
    ex_chol = model[M_EX_CHOL]
    terrain_w = model[M_TERRAIN_W]
    task_kind = task[T_KIND]
    seg = task[T_SEG]
    cell_start = task[T_CELL_START]
    candidates = task[T_CANDIDATES]
    field = task[T_FIELD]
    grid_origin = task[T_ORIGIN]
    inv_cell = task[T_INV_CELL]
    half_width = task[T_HALF_WIDTH]
    tightened_hw = task[T_TIGHTENED_HW]
    speed_target = task[T_SPEED_TARGET]
    goal = task[T_GOAL]
    obstacles = task[T_OBSTACLES]
    radii = task[T_RADII]
    x0 = sampling[S_X0]
    nominal = sampling[S_NOMINAL]
    noise_std = sampling[S_NOISE_STD]
    u_lo = sampling[S_U_LO]
    u_hi = sampling[S_U_HI]
    dt = sampling[S_DT]
    seed = sampling[S_SEED]
    iteration = sampling[S_ITERATION]
    eps_out = out[O_EPS]
    cost_out = out[O_COST]
    xy_out = out[O_XY]
    cost_w = weight_vector(cost)
    discount = cost_w[K_EXIT_DISCOUNT]
    samples = eps_out.shape[0]
    horizon = nominal.shape[0]
    n_xy = xy_out.shape[0]
    n_tasks = ex_alpha.shape[0]
    n_train = ex_alpha.shape[1]
    n_groups = (samples + GROUP - 1) // GROUP
    counter0 = iteration * samples
    coef = velocity_coefficients(theta, lateral)
    (lo0, lo1, lo2, lo3, inv0, inv1, inv2, inv3, top0, top1, top2, top3, last0, last1, last2, last3, s0, s1,
     s2) = simplex_params(dims, lo, inv_step)
    flat = table.reshape(-1)  # the (nodes, 4) table as one run of floats
    for g in prange(n_groups):
        # the helpers' inputs grouped once per group, from the locals above
        grid = (lo0, lo1, lo2, lo3, inv0, inv1, inv2, inv3, top0, top1, top2, top3, last0, last1, last2, last3, s0, s1,
                s2)
        limits = (nominal, noise_std, u_lo, u_hi)
        gp = (gp_mode, table, dims, lo, inv_step, ex_scaled_x, ex_inv_ls, ex_outputscale, ex_alpha, ex_chol,
              terrain_w)
        geo = (seg, cell_start, candidates, field, grid_origin, inv_cell, half_width, speed_target, goal, obstacles)
        scratch = (np.empty(n_train), np.empty(n_tasks), np.empty(n_tasks))
        first = g * GROUP
        n_in = min(GROUP, samples - first)
        st = np.empty((GROUP, 5))
        total = np.zeros(GROUP)
        # commands of the previous, this and the next step (rotated every step)
        cmd_prev = np.empty((GROUP, 2))
        cmd = np.empty((GROUP, 2))
        cmd_next = np.empty((GROUP, 2))
        res = np.zeros((GROUP, 4))  # GP residual [mean_v, mean_w, var_v, var_w]; zero for the other models
        # simplex node indices and weights of the group, one row per vertex: unit-stride rows let the loop that
        # fills them run as vector code
        nodes = np.zeros((5, GROUP), dtype=np.uint64)
        node_w = np.zeros((5, GROUP), dtype=np.float32)
        for j in range(n_in):
            for i in range(5):
                st[j, i] = x0[i]
            if first + j < n_xy:
                xy_out[first + j, 0, 0] = x0[0]
                xy_out[first + j, 0, 1] = x0[1]
        _draw_commands(seed, counter0, horizon, 0, limits, first, n_in, eps_out, cmd)
        discount_k = 1.0  # discount of step k - 1's cost
        # Step k: (1) the GP table rows of step k are requested (prefetch), (2) the next step's commands are
        # drawn and (3) the previous step's cost is added, both needing no table, while the rows arrive from
        # memory, (4) the rows are read, (5) the states advance. Costs are added in step order as before.
        for k in range(horizon):
            if dyn_mode == DYN_GP and gp_mode == GP_SIMPLEX:
                # a loop of its own, free of the noise's library calls and of branches, so that it is vectorised
                for j in range(n_in):
                    n0, t0, t1, t2, t3, w0, w1, w2, w3, w4 = simplex_corner(grid, st[j, 3], st[j, 4], cmd[j, 0],
                                                                            cmd[j, 1])
                    nodes[0, j] = n0
                    nodes[1, j] = n0 + t0
                    nodes[2, j] = n0 + t0 + t1
                    nodes[3, j] = n0 + t0 + t1 + t2
                    nodes[4, j] = n0 + t0 + t1 + t2 + t3
                    node_w[0, j] = w0
                    node_w[1, j] = w1
                    node_w[2, j] = w2
                    node_w[3, j] = w3
                    node_w[4, j] = w4
                for j in range(n_in):
                    for q in range(5):
                        prefetch_row(table, nodes[q, j])
            if k + 1 < horizon:
                _draw_commands(seed, counter0, horizon, k + 1, limits, first, n_in, eps_out, cmd_next)
            if k > 0:
                _add_costs(n_in, st, cmd_prev, res, total, task_kind, cost_w, geo, (tightened_hw[k], radii[k]),
                           discount_k)
                discount_k *= discount
            if dyn_mode == DYN_GP and gp_mode == GP_SIMPLEX:
                for j in range(n_in):
                    # flat offsets, unsigned: no negative-index wrap-around and no multiply by the row length
                    n = np.uint64(4) * nodes[0, j]
                    wq = node_w[0, j]
                    c0 = wq * flat[n]
                    c1 = wq * flat[n + np.uint64(1)]
                    c2 = wq * flat[n + np.uint64(2)]
                    c3 = wq * flat[n + np.uint64(3)]
                    for q in range(1, 5):
                        n = np.uint64(4) * nodes[q, j]
                        wq = node_w[q, j]
                        c0 += wq * flat[n]
                        c1 += wq * flat[n + np.uint64(1)]
                        c2 += wq * flat[n + np.uint64(2)]
                        c3 += wq * flat[n + np.uint64(3)]
                    res[j, 0] = c0
                    res[j, 1] = c1
                    res[j, 2] = c2
                    res[j, 3] = c3
            elif dyn_mode == DYN_GP:
                for j in range(n_in):
                    res[j, 0], res[j, 1], res[j, 2], res[j, 3] = gp_residual(gp, scratch, cmd[j, 0], cmd[j, 1],
                                                                             st[j, 3], st[j, 4])
            for j in range(n_in):
                s = first + j
                px, py, yaw, v, w = advance(dyn_mode, dt, coef, edd5_p,
                                            (st[j, 0], st[j, 1], st[j, 2], st[j, 3], st[j, 4]), (cmd[j, 0], cmd[j, 1]),
                                            res[j, 0], res[j, 1])
                st[j, 0] = px
                st[j, 1] = py
                st[j, 2] = yaw
                st[j, 3] = v
                st[j, 4] = w
                if s < n_xy:
                    xy_out[s, k + 1, 0] = px
                    xy_out[s, k + 1, 1] = py
            cmd_prev, cmd, cmd_next = cmd, cmd_next, cmd_prev
        _add_costs(n_in, st, cmd_prev, res, total, task_kind, cost_w, geo, (tightened_hw[horizon], radii[horizon]),
                   discount_k)
        for j in range(n_in):
            t = total[j]
            if task_kind == TASK_GOAL:
                t += goal_term(cost_w, field, grid_origin, inv_cell, goal, st[j, 0], st[j, 1],
                               cost_w[K_TERMINAL])
            if not np.isfinite(t):
                t = np.inf
            cost_out[first + j] = t


@njit(cache=True, fastmath=FASTMATH)
def nominal_critic_costs(model: tuple, task: tuple, sampling: tuple, cost: tuple) -> np.ndarray:
    """Each critic's cost (`CRITICS` order) of the sampling bundle's nominal sequence, clipped to its limits.

    Serial, one rollout with the model's own step (`step_state`), compiled with the kernels' flags (without them
    the float32 cos/sin and table reads round differently and the sum strayed 5e-9 from the kernel's cost): the
    kernels add the critics of a step into one cost, this keeps them apart; their sum is the kernels' cost.
    """
    kind = task[T_KIND]
    tightened_hw = task[T_TIGHTENED_HW]
    radii = task[T_RADII]
    geo = (task[T_SEG], task[T_CELL_START], task[T_CANDIDATES], task[T_FIELD], task[T_ORIGIN], task[T_INV_CELL],
           task[T_HALF_WIDTH], task[T_SPEED_TARGET], task[T_GOAL], task[T_OBSTACLES])
    nominal = sampling[S_NOMINAL]
    u_lo = sampling[S_U_LO]
    u_hi = sampling[S_U_HI]
    dt = sampling[S_DT]
    dyn = (model[M_DYN_MODE], velocity_coefficients(model[M_THETA], model[M_LATERAL]), model[M_EDD5])
    gp = gp_inputs(model)
    scratch = gp_scratch(model)
    cost_w = weight_vector(cost)
    discount = cost_w[K_EXIT_DISCOUNT]
    x0 = sampling[S_X0]
    s = (x0[0], x0[1], x0[2], x0[3], x0[4])
    out = np.zeros(len(CRITICS))
    discount_k = 1.0
    for k in range(nominal.shape[0]):
        u = (clip(nominal[k, 0], u_lo[0], u_hi[0]), clip(nominal[k, 1], u_lo[1], u_hi[1]))
        px, py, yaw, v, w, _mv, _mw, var_v, var_w = step_state(dyn, gp, scratch, dt, s, u)
        s = (px, py, yaw, v, w)
        stage_critics(kind, cost_w, geo, tightened_hw[k + 1], radii[k + 1], discount_k, s, u, (var_v, var_w), out)
        discount_k *= discount
    if kind == TASK_GOAL:
        out[K_TERMINAL] += goal_term(cost_w, task[T_FIELD], task[T_ORIGIN], task[T_INV_CELL],
                                     task[T_GOAL], s[0], s[1], cost_w[K_TERMINAL])
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
