"""CUDA backend: one thread per sample runs the whole horizon (noise, model, grid GP, costs) in one launch.

Every equation is the CPU kernel's own (`cpu_backend.rollout_kernel`): the device functions here are
compiled from the CPU functions' Python (`gpmppi.gp.cuda_kernels.device_version`), and the same
counter-based noise is drawn, so both backends agree to rounding. The exact GP runs on the CPU
backend only (`Planner` refuses `backend="cuda"` with `gp_mode="exact"`).

Tested under the CUDA simulator (`NUMBA_ENABLE_CUDASIM=1`) against the CPU backend, and compiled to
PTX for a real GPU by `tests/test_cuda_compiles.py` (the simulator runs plain Python, which proves
nothing about what numba's CUDA target accepts).
"""

from __future__ import annotations

import math

import numpy as np
from numba import cuda

from gpmppi.gp.cuda_kernels import device_version
from gpmppi.mppi import costs as critic
from gpmppi.mppi import dynamics, gp_table, rng
from gpmppi.mppi.dynamics import DYN_GP, GP_EXACT, GP_SIMPLEX, velocity_coefficients

THREADS_PER_BLOCK = 128


_noisy_command = device_version(rng.noisy_command)
_interp4 = device_version(gp_table.interp4)
_interp4_simplex = device_version(gp_table.interp4_simplex)
_advance = device_version(dynamics.advance)
_stage_cost = device_version(critic.stage_cost)
_goal_term = device_version(critic.goal_term)


@cuda.jit(cache=True)
def _rollout_kernel(
    x0, nominal, noise_std, u_lo, u_hi, dt, seed, iteration, dyn_mode, coef, edd5_p, gp_mode, table, dims, lo,
    inv_step, task_kind, seg, cell_start, candidates, field, grid_origin, inv_cell, half_width, tightened_hw,
    speed_target, goal, obstacles, radii, cost_w, eps_out, cost_out, xy_out,
):
    s = cuda.grid(1)
    samples = eps_out.shape[0]
    if s >= samples:
        return
    horizon = nominal.shape[0]
    n_xy = xy_out.shape[0]
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
    discount = cost_w[critic.W_EXIT_DISCOUNT]
    base = (iteration * samples + s) * horizon
    for k in range(horizon):
        u0, u1 = _noisy_command(seed, base + k, nominal, k, noise_std, u_lo, u_hi)
        eps_out[s, k, 0] = u0 - nominal[k, 0]
        eps_out[s, k, 1] = u1 - nominal[k, 1]
        mv = 0.0
        mw = 0.0
        cv = 0.0
        cw = 0.0
        if dyn_mode == DYN_GP:
            if gp_mode == GP_SIMPLEX:
                mv, mw, cv, cw = _interp4_simplex(table, dims, lo, inv_step, v, w, u0, u1)
            else:
                mv, mw, cv, cw = _interp4(table, dims, lo, inv_step, v, w, u0, u1)
        px, py, yaw, v, w = _advance(dyn_mode, dt, coef, edd5_p, px, py, yaw, v, w, u0, u1, mv, mw)
        if s < n_xy:
            xy_out[s, k + 1, 0] = px
            xy_out[s, k + 1, 1] = py
        total += _stage_cost(task_kind, cost_w, seg, cell_start, candidates, field, grid_origin, inv_cell, half_width,
                             tightened_hw[k + 1], speed_target, goal, obstacles, radii[k + 1], discount_k, px, py,
                             yaw, v, w, u0, u1, cv, cw)
        discount_k *= discount
    if task_kind == critic.TASK_GOAL:
        total += _goal_term(cost_w, field, grid_origin, inv_cell, goal, px, py, cost_w[critic.W_TERMINAL])
    if math.isnan(total) or math.isinf(total):
        total = math.inf
    cost_out[s] = total


def cuda_rollouts(args: tuple, eps: np.ndarray, costs: np.ndarray, xy: np.ndarray) -> None:
    """Run the kernel with the CPU kernel's argument tuple (see `backends.rollouts`); fill eps, costs, xy."""
    (x0, nominal, noise_std, u_lo, u_hi, dt, seed, iteration, dyn_mode, theta, lateral, edd5_p, gp_mode, table, dims,
     lo, inv_step, _sx, _il, _os, _al, _ch, _tw, task_kind, seg, cell_start, candidates, field, grid_origin, inv_cell,
     half_width, tightened_hw, speed_target, goal, obstacles, radii, cost_w) = args
    if dyn_mode == DYN_GP and gp_mode == GP_EXACT:
        raise ValueError("the CUDA backend evaluates the GP by grid only; use gp_mode='grid' or backend='cpu'")
    dev = cuda.to_device
    d_eps = cuda.device_array(eps.shape, dtype=eps.dtype)
    d_costs = cuda.device_array(costs.shape, dtype=costs.dtype)
    d_xy = cuda.device_array(xy.shape if xy.size else (0, nominal.shape[0] + 1, 2), dtype=xy.dtype)
    blocks = (eps.shape[0] + THREADS_PER_BLOCK - 1) // THREADS_PER_BLOCK
    # (under the simulator numpy runs the uint64 hash and warns about its intended wrap-around)
    _rollout_kernel[blocks, THREADS_PER_BLOCK](
        dev(x0), dev(nominal), dev(noise_std), dev(u_lo), dev(u_hi), dt, np.int64(seed), np.int64(iteration),
        dyn_mode, dev(velocity_coefficients(theta, lateral)), dev(edd5_p), gp_mode, dev(table), dev(dims), dev(lo),
        dev(inv_step), task_kind, dev(seg), dev(cell_start), dev(candidates), dev(field), dev(grid_origin), inv_cell,
        half_width, dev(tightened_hw), speed_target, dev(goal), dev(obstacles), dev(radii), dev(cost_w), d_eps,
        d_costs, d_xy,
    )
    d_eps.copy_to_host(eps)
    d_costs.copy_to_host(costs)
    if xy.size:
        d_xy.copy_to_host(xy)
