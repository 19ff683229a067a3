"""CUDA backend: one thread per sample runs the whole horizon (noise, model, grid GP, costs) in one launch.

Same math and the same counter-based noise as the CPU kernel (`cpu_backend.rollout_kernel`), so
both backends agree to rounding (single- vs double-precision transcendentals). Leaf functions
(noise, cost terms, segment distance) are compiled from the very Python source the CPU backend
compiles; functions that call others are written out here as device functions. The grid GP
interpolations (simplex and multilinear) are this file's own device functions. The exact GP runs on the CPU backend only
(`Planner` refuses `backend="cuda"` with `gp_mode="exact"`).

Tested under the CUDA simulator (`NUMBA_ENABLE_CUDASIM=1`) against the CPU backend.
"""

from __future__ import annotations

import math

import numpy as np
from numba import cuda

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
    deviation_cost,
    goal_cost,
    lane_exit_cost,
    slip_cost,
    speed_cost,
    variance_cost,
)
from gpmppi.models.edd5 import TRACK_B, WHEEL_R
from gpmppi.mppi.dynamics import DYN_EDD5, DYN_GP, GP_EXACT, GP_SIMPLEX
from gpmppi.mppi.dynamics import _cswap as cswap
from gpmppi.mppi.lane import segment_distance2
from gpmppi.mppi.rng import _normal_pair_py

THREADS_PER_BLOCK = 128
TASK_LANE = 0

_normal_pair = cuda.jit(device=True)(_normal_pair_py)
_variance_cost = cuda.jit(device=True)(variance_cost.py_func)
_deviation_cost = cuda.jit(device=True)(deviation_cost.py_func)
_slip_cost = cuda.jit(device=True)(slip_cost.py_func)
_lane_exit_cost = cuda.jit(device=True)(lane_exit_cost.py_func)
_speed_cost = cuda.jit(device=True)(speed_cost.py_func)
_goal_cost = cuda.jit(device=True)(goal_cost.py_func)
_segment_distance2 = cuda.jit(device=True)(segment_distance2.py_func)
_cswap = cuda.jit(device=True)(cswap.py_func)


@cuda.jit(device=True)
def _collision_cost(x, y, obstacles, radii, k, weight):
    for j in range(obstacles.shape[0]):
        dx = x - obstacles[j, 0]
        dy = y - obstacles[j, 1]
        r = radii[k, j]
        if dx * dx + dy * dy < r * r:
            return weight
    return 0.0


@cuda.jit(device=True)
def _lane_distance_near(seg, cell_start, cand, field, origin, inv_cell, x, y, threshold):
    h = field.shape[0]
    w = field.shape[1]
    fc = (x - origin[0]) * inv_cell - 0.5
    fr = (y - origin[1]) * inv_cell - 0.5
    if fc >= 0.0 and fr >= 0.0 and fc < w - 1 and fr < h - 1:
        c = int(fc)
        r = int(fr)
        tx = fc - c
        ty = fr - r
        d = (1.0 - ty) * ((1.0 - tx) * field[r, c] + tx * field[r, c + 1]) + ty * (
            (1.0 - tx) * field[r + 1, c] + tx * field[r + 1, c + 1]
        )
        if abs(d - threshold) > 1.4143 / inv_cell:
            return d
    best = math.inf
    cc = (x - origin[0]) * inv_cell
    rr = (y - origin[1]) * inv_cell
    if cc >= 0.0 and rr >= 0.0 and cc < w and rr < h:
        i = int(rr) * w + int(cc)
        for q in range(cell_start[i], cell_start[i + 1]):
            best = min(best, _segment_distance2(seg, cand[q], x, y))
    else:
        for j in range(seg.shape[0]):
            best = min(best, _segment_distance2(seg, j, x, y))
    return math.sqrt(best)


@cuda.jit(device=True)
def _axis(x, lo, inv_step, g):
    t = (x - lo) * inv_step
    if t <= 0.0:
        return 0, 0.0
    if t >= g - 1:
        return g - 2, 1.0
    i = int(t)
    return i, t - i


@cuda.jit(device=True)
def _interp4(table, dims, lo, inv_step, a0, a1, a2, a3):
    i0, f0 = _axis(a0, lo[0], inv_step[0], dims[0])
    i1, f1 = _axis(a1, lo[1], inv_step[1], dims[1])
    i2, f2 = _axis(a2, lo[2], inv_step[2], dims[2])
    i3, f3 = _axis(a3, lo[3], inv_step[3], dims[3])
    s2 = dims[3]
    s1 = dims[2] * s2
    s0 = dims[1] * s1
    base = i0 * s0 + i1 * s1 + i2 * s2 + i3
    c0 = 0.0
    c1 = 0.0
    c2 = 0.0
    c3 = 0.0
    for b in range(8):
        b0 = b >> 2
        b1 = (b >> 1) & 1
        b2 = b & 1
        w = (f0 if b0 else 1.0 - f0) * (f1 if b1 else 1.0 - f1) * (f2 if b2 else 1.0 - f2)
        lo_w = w * (1.0 - f3)
        hi_w = w * f3
        n = base + b0 * s0 + b1 * s1 + b2 * s2
        c0 += lo_w * table[n, 0] + hi_w * table[n + 1, 0]
        c1 += lo_w * table[n, 1] + hi_w * table[n + 1, 1]
        c2 += lo_w * table[n, 2] + hi_w * table[n + 1, 2]
        c3 += lo_w * table[n, 3] + hi_w * table[n + 1, 3]
    return c0, c1, c2, c3


@cuda.jit(device=True)
def _interp4_simplex(table, dims, lo, inv_step, a0, a1, a2, a3):
    i0, f0 = _axis(a0, lo[0], inv_step[0], dims[0])
    i1, f1 = _axis(a1, lo[1], inv_step[1], dims[1])
    i2, f2 = _axis(a2, lo[2], inv_step[2], dims[2])
    i3, f3 = _axis(a3, lo[3], inv_step[3], dims[3])
    s3 = 1
    s2 = dims[3]
    s1 = dims[2] * s2
    s0 = dims[1] * s1
    n = i0 * s0 + i1 * s1 + i2 * s2 + i3
    f0, s0, f1, s1 = _cswap(f0, s0, f1, s1)
    f2, s2, f3, s3 = _cswap(f2, s2, f3, s3)
    f0, s0, f2, s2 = _cswap(f0, s0, f2, s2)
    f1, s1, f3, s3 = _cswap(f1, s1, f3, s3)
    f1, s1, f2, s2 = _cswap(f1, s1, f2, s2)
    c0 = 0.0
    c1 = 0.0
    c2 = 0.0
    c3 = 0.0
    for j in range(5):
        if j == 0:
            wj = 1.0 - f0
        elif j == 1:
            n += s0
            wj = f0 - f1
        elif j == 2:
            n += s1
            wj = f1 - f2
        elif j == 3:
            n += s2
            wj = f2 - f3
        else:
            n += s3
            wj = f3
        c0 += wj * table[n, 0]
        c1 += wj * table[n, 1]
        c2 += wj * table[n, 2]
        c3 += wj * table[n, 3]
    return c0, c1, c2, c3


@cuda.jit(device=True)
def _step_state(dyn_mode, dt, theta, edd5_p, gp_mode, table, dims, lo, inv_step, px, py, yaw, v, w, u0, u1):
    cy = math.cos(np.float32(yaw))
    sy = math.sin(np.float32(yaw))
    if dyn_mode == DYN_GP:
        if gp_mode == GP_SIMPLEX:
            mv, mw, cv, cw = _interp4_simplex(table, dims, lo, inv_step, v, w, u0, u1)
        else:
            mv, mw, cv, cw = _interp4(table, dims, lo, inv_step, v, w, u0, u1)
        vdot = (theta[2] / theta[0]) * w * w - (theta[3] / theta[0]) * v + u0 / theta[0]
        wdot = -(theta[4] / theta[1]) * v * w - (theta[5] / theta[1]) * w + u1 / theta[1]
        return px + v * cy * dt, py + v * sy * dt, yaw + w * dt, v + vdot * dt + mv, w + wdot * dt + mw, cv, cw
    if dyn_mode == DYN_EDD5:
        w_r = (u0 + 0.5 * u1 * TRACK_B) / WHEEL_R
        w_l = (u0 - 0.5 * u1 * TRACK_B) / WHEEL_R
        kk = WHEEL_R / (edd5_p[4] - edd5_p[3])
        v1 = kk * (-edd5_p[3] * edd5_p[1] * w_l + edd5_p[4] * edd5_p[0] * w_r)
        w1 = kk * (-edd5_p[1] * w_l + edd5_p[0] * w_r)
    else:
        v1 = u0
        w1 = u1
    return px + v1 * cy * dt, py + v1 * sy * dt, yaw + w1 * dt, v1, w1, 0.0, 0.0


@cuda.jit(cache=True)
def _rollout_kernel(
    x0, nominal, noise_std, u_lo, u_hi, dt, seed, iteration, dyn_mode, theta, edd5_p, gp_mode, table, dims, lo,
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
    discount = cost_w[W_EXIT_DISCOUNT]
    base = (iteration * samples + s) * horizon
    for k in range(horizon):
        z0, z1 = _normal_pair(seed, base + k)
        u0 = min(max(nominal[k, 0] + noise_std[0] * z0, u_lo[0]), u_hi[0])
        u1 = min(max(nominal[k, 1] + noise_std[1] * z1, u_lo[1]), u_hi[1])
        eps_out[s, k, 0] = u0 - nominal[k, 0]
        eps_out[s, k, 1] = u1 - nominal[k, 1]
        px, py, yaw, v, w, cv, cw = _step_state(dyn_mode, dt, theta, edd5_p, gp_mode, table, dims, lo, inv_step,
                                                px, py, yaw, v, w, u0, u1)
        if s < n_xy:
            xy_out[s, k + 1, 0] = px
            xy_out[s, k + 1, 1] = py
        c = _variance_cost(cv, cw, cost_w[W_VARIANCE])
        if task_kind == TASK_LANE:
            d = _lane_distance_near(seg, cell_start, candidates, field, grid_origin, inv_cell, px, py,
                                    tightened_hw[k + 1])
            c += _deviation_cost(d, half_width, cost_w[W_DEVIATION])
            c += _slip_cost(v, w, u0, u1, cost_w[W_SLIP])
            c += _lane_exit_cost(d, tightened_hw[k + 1], discount_k, cost_w[W_LANE_EXIT])
            c += _speed_cost(v, speed_target, cost_w[W_SPEED])
        else:
            c += _collision_cost(px, py, obstacles, radii, k + 1, cost_w[W_COLLISION])
            c += _goal_cost(px, py, goal, cost_w[W_GOAL])
        total += c
        discount_k *= discount
    if task_kind != TASK_LANE:
        total += _goal_cost(px, py, goal, cost_w[W_TERMINAL])
    if math.isnan(total) or math.isinf(total):
        total = math.inf
    cost_out[s] = total


def cuda_rollouts(args: tuple, eps: np.ndarray, costs: np.ndarray, xy: np.ndarray) -> None:
    """Run the kernel with the CPU kernel's argument tuple (see `backends.rollouts`); fill eps, costs, xy."""
    (x0, nominal, noise_std, u_lo, u_hi, dt, seed, iteration, dyn_mode, theta, edd5_p, gp_mode, table, dims, lo,
     inv_step, _sx, _il, _os, _al, _ch, _tw, task_kind, seg, cell_start, candidates, field, grid_origin, inv_cell,
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
        dyn_mode, dev(theta), dev(edd5_p), gp_mode, dev(table), dev(dims), dev(lo), dev(inv_step), task_kind, dev(seg),
        dev(cell_start), dev(candidates), dev(field), dev(grid_origin), inv_cell, half_width, dev(tightened_hw),
        speed_target, dev(goal), dev(obstacles), dev(radii), dev(cost_w), d_eps, d_costs, d_xy,
    )
    d_eps.copy_to_host(eps)
    d_costs.copy_to_host(costs)
    if xy.size:
        d_xy.copy_to_host(xy)
