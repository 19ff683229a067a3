"""One rollout step of each planner model with the weighted-ensemble GP residual, and covariance propagation.

Models (`DYN_*`): the kinematic unicycle; EDD5 of one terrain; the nominal dynamic unicycle
(explicit Euler on the velocities, second order on the pose: `nominal_step`) plus the weighted GP ensemble
residual on the velocities,
mean `sum_i w_i m_i`, variance `sum_i w_i^2 C_i` (C = latent variance), and the terrain-weighted sideways slide
of a skid-steer turn on the pose (`gpmppi.models.lateral_slip`).

GP evaluation (`GP_*`): `grid` interpolates (simplex or multilinear) the collapsed table of
[mean_v, mean_w, var_v, var_w] (`gpmppi.mppi.gp_table`); `exact` evaluates the exact GP
(`gpmppi.gp.exact.exact_tasks`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from gpmppi.gp.exact import exact_tasks
from gpmppi.gp.grid_interp import grid_cell
from gpmppi.kernel_flags import FASTMATH
from gpmppi.models.dynamic_unicycle import jacobian_into
from gpmppi.models.edd5 import edd5_velocity
from gpmppi.models.lateral_slip import lateral_velocity
from gpmppi.mppi.gp_table import cell32, interp4, interp4_simplex, simplex_params
from gpmppi.mppi.lazy_collapse import ensure_block
from gpmppi.trig import cos_sin

DYN_UNICYCLE = 0
DYN_EDD5 = 1
DYN_GP = 2
GP_GRID = 0  # grid table, multilinear interpolation (16 nodes)
GP_EXACT = 1  # exact GP
GP_SIMPLEX = 2  # grid table, simplex interpolation (5 nodes)


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def gp_residual(
    gp: tuple, scratch: tuple, v_ref: float, w_ref: float, v: float, w: float
) -> tuple[float, float, float, float]:
    """Ensemble residual (mean_v, mean_w, var_v, var_w) at GP input [v_ref, w_ref, v, w].

    `gp` = `gp_inputs(...)` of the model bundle's fields; `scratch` = (work (n,), mean (2M,), var (2M,)) for the
    exact GP. Grid mode: `table`, `lo`, `inv_step` are in the collapsed table's axis order (`TABLE_AXES`).
    """
    (gp_mode, table, dims, lo, inv_step, ex_scaled_x, ex_inv_ls, ex_outputscale, ex_alpha, ex_chol, terrain_w,
     table_src, lazy, collapse_w) = gp
    if gp_mode == GP_SIMPLEX:
        if lazy[0] != 0:  # a lazily collapsed table: the slabs of the cell the lookup reads, by its own cells
            g = simplex_params(dims, lo, inv_step)
            i0, _ = cell32(v, g[0], g[4], g[8], g[12])
            i1, _ = cell32(w, g[1], g[5], g[9], g[13])
            i2, _ = cell32(v_ref, g[2], g[6], g[10], g[14])
            ensure_block(lazy, table_src, collapse_w, table, dims, i0, i1, i2)
        return interp4_simplex(table, dims, lo, inv_step, v, w, v_ref, w_ref)
    if gp_mode == GP_GRID:
        if lazy[0] != 0:
            i0, _ = grid_cell(v, lo[0], inv_step[0], dims[0])
            i1, _ = grid_cell(w, lo[1], inv_step[1], dims[1])
            i2, _ = grid_cell(v_ref, lo[2], inv_step[2], dims[2])
            ensure_block(lazy, table_src, collapse_w, table, dims, i0, i1, i2)
        return interp4(table, dims, lo, inv_step, v, w, v_ref, w_ref)
    work, gp_mean, gp_var = scratch
    exact_tasks(v_ref, w_ref, v, w, ex_scaled_x, ex_inv_ls, ex_outputscale, ex_alpha, ex_chol, work, gp_mean, gp_var,
                True)
    mv = 0.0
    mw = 0.0
    cv = 0.0
    cw = 0.0
    for t in range(terrain_w.shape[0]):
        wt = terrain_w[t]
        mv += wt * gp_mean[2 * t]
        mw += wt * gp_mean[2 * t + 1]
        cv += wt * wt * gp_var[2 * t]
        cw += wt * wt * gp_var[2 * t + 1]
    return mv, mw, cv, cw


@njit(cache=True, inline="always")
def gp_inputs(model: tuple) -> tuple:
    """The GP fields of a model bundle's tuple, as `gp_residual` takes them (called once, before any loop)."""
    return (model.gp_mode, model.table, model.dims, model.lo, model.inv_step, model.ex_scaled_x,
            model.ex_inv_ls, model.ex_outputscale, model.ex_alpha, model.ex_chol, model.terrain_w,
            model.table_src, model.lazy, model.collapse_w)


@njit(cache=True, inline="always")
def gp_scratch(model: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Work arrays of the exact GP for one thread: (n,) and the (2M,) means and variances."""
    alpha = model.ex_alpha
    return np.empty(alpha.shape[1]), np.empty(alpha.shape[0]), np.empty(alpha.shape[0])


@njit(cache=True, inline="always")
def fill_velocity_coefficients(theta: np.ndarray, lateral: np.ndarray, coef: np.ndarray) -> None:
    """Write [th3/th1, th4/th1, 1/th1, th5/th2, th6/th2, 1/th2, a, b] into `coef` (8,): divisions done once, not at
    every sample-step; (a, b) the terrain-weighted lateral slip coefficients (`gpmppi.models.lateral_slip`). The CUDA
    kernel fills a thread's own array with it (a device function cannot make an array)."""
    coef[0] = theta[2] / theta[0]
    coef[1] = theta[3] / theta[0]
    coef[2] = 1.0 / theta[0]
    coef[3] = theta[4] / theta[1]
    coef[4] = theta[5] / theta[1]
    coef[5] = 1.0 / theta[1]
    coef[6] = lateral[0]
    coef[7] = lateral[1]


@njit(cache=True, inline="always")
def velocity_coefficients(theta: np.ndarray, lateral: np.ndarray) -> np.ndarray:
    """`fill_velocity_coefficients` into a new array."""
    coef = np.empty(8)
    fill_velocity_coefficients(theta, lateral, coef)
    return coef


@njit(cache=True, inline="always")
def dyn_inputs(model: tuple, coef: np.ndarray) -> tuple:
    """The model fields of a model bundle's tuple as `step_state` takes them, (dyn_mode, coef, edd5), with `coef` its
    `velocity_coefficients` (called once, before any loop)."""
    return (model.dyn_mode, coef, model.edd5)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def nominal_velocity_step(
    coef: np.ndarray, v: float, w: float, v_ref: float, w_ref: float, dt: float
) -> tuple[float, float]:
    """Explicit-Euler velocity step of the nominal dynamic unicycle (as `nominal_step`); `velocity_coefficients`."""
    vdot = coef[0] * w * w - coef[1] * v + v_ref * coef[2]
    wdot = -coef[3] * v * w - coef[4] * w + w_ref * coef[5]
    return v + vdot * dt, w + wdot * dt


@njit(cache=True, fastmath=FASTMATH, inline="always")
def advance(
    dyn_mode: int, dt: float, coef: np.ndarray, edd5_p: np.ndarray, s: tuple, u: tuple, mv: float, mw: float,
) -> tuple[float, float, float, float, float]:
    """Next state (5 scalars) of the chosen model from state `s` (5 scalars) under command `u` (2); GP model:
    (mv, mw) is the step's residual mean. `coef` = `velocity_coefficients(theta, lateral)`."""
    px, py, yaw, v, w = s
    u0, u1 = u
    if dyn_mode == DYN_GP:
        v1, w1 = nominal_velocity_step(coef, v, w, u0, u1, dt)
        v1 += mv
        w1 += mw
        # dynamic model: the pose advances with the mean of the step's start and end velocities, along the
        # heading at mid-step (second order; with the start velocities alone a yaw rate changing by 1 rad/s in
        # a step puts the pose 0.05 rad behind), plus the sideways slide of a skid-steer turn
        vm = 0.5 * (v + v1)
        wm = 0.5 * (w + w1)
        vy = lateral_velocity(coef[6], coef[7], vm, wm)
        c, s_ = cos_sin(yaw + 0.5 * wm * dt)
        return px + (vm * c - vy * s_) * dt, py + (vm * s_ + vy * c) * dt, yaw + wm * dt, v1, w1
    c, s_ = cos_sin(yaw)
    if dyn_mode == DYN_EDD5:
        v1, w1 = edd5_velocity(edd5_p, u0, u1)
    else:
        v1 = u0
        w1 = u1
    # kinematic models: velocities follow the command at once, then the pose advances
    return px + v1 * c * dt, py + v1 * s_ * dt, yaw + w1 * dt, v1, w1


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def step_state(
    dyn: tuple, gp: tuple, scratch: tuple, dt: float, s: tuple, u: tuple, residual_scale: float,
) -> tuple[float, float, float, float, float, float, float, float, float]:
    """Next state (5 scalars) of the chosen model, the residual means it added (mean_v, mean_w) and the step's
    residual variances (var_v, var_w). `dyn` = (dyn_mode, coef, edd5_p), `gp` and `scratch` as `gp_residual`;
    `s` the state (5 scalars), `u` the command (2). `residual_scale` < 1 adds that share of the residual mean
    (a step shorter than the GP's).

    The one model step of the serial kernels (`propagate`, `predict_ahead`, the per-critic scorer): a function
    of its own, compiled once and called by each (inlined into each, it was compiled three times over)."""
    dyn_mode, coef, edd5_p = dyn
    mv = 0.0
    mw = 0.0
    cv = 0.0
    cw = 0.0
    if dyn_mode == DYN_GP:
        mv, mw, cv, cw = gp_residual(gp, scratch, u[0], u[1], s[3], s[4])
        mv *= residual_scale
        mw *= residual_scale
    px, py, yaw, v, w = advance(dyn_mode, dt, coef, edd5_p, s, u, mv, mw)
    return px, py, yaw, v, w, mv, mw, cv, cw


@njit(cache=True, inline="always")
def _product5(a: np.ndarray, b: np.ndarray, b_transposed: bool, out: np.ndarray) -> None:
    """out = a b (or a b^T) for 5x5 matrices, in plain loops (a BLAS call per step costs more than the flops)."""
    for i in range(5):
        for j in range(5):
            acc = 0.0
            for q in range(5):
                acc += a[i, q] * (b[j, q] if b_transposed else b[q, j])
            out[i, j] = acc


@njit(cache=True, inline="always")
def _sandwich(a: np.ndarray, b: np.ndarray, tmp: np.ndarray, out: np.ndarray) -> None:
    """out = a b a^T for 5x5 matrices."""
    _product5(a, b, False, tmp)
    _product5(tmp, a, True, out)


@njit(cache=True)
def propagate(
    model: tuple, x0: np.ndarray, controls: np.ndarray, dt: float, noise_v: float = 0.0, noise_w: float = 0.0,
    cov0: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean states (N+1, 5), covariances (N+1, 5, 5) and step variances (N, 2) along `controls` by the model of
    `model` (`ModelBundle.args()`).

    `cov0` (5, 5) is the covariance of the start state (the state estimate's), zero when None.

    GP model: Sigma+ = J Sigma J^T + diag(0, 0, 0, C_v + noise_v, C_w + noise_w) with J the Jacobian of
    `nominal_step` at (x_k, u_k) and the step's mean residual, C the ensemble's latent variance; `noise_v`,
    `noise_w` are the ensemble's likelihood noise `sum_i w_i^2 noise_i` (with it the added term is the GP's
    predictive variance of the next velocity, which is what the data scatter by). The mean includes the GP mean
    residual. Other models carry no uncertainty, so their covariances stay zero. The returned step
    variances are the predictive ones too.
    """
    dyn_mode = model.dyn_mode
    theta = model.theta
    lateral = model.lateral
    dyn = dyn_inputs(model, velocity_coefficients(theta, lateral))
    gp = gp_inputs(model)
    scratch = gp_scratch(model)
    n = controls.shape[0]
    states = np.zeros((n + 1, 5))
    covs = np.zeros((n + 1, 5, 5))
    step_var = np.zeros((n, 2))
    # element by element: numba's whole-array assignment brings a shape-mismatch error path whose message
    # formatting took seconds to compile
    for i in range(5):
        states[0, i] = x0[i]
    if cov0 is not None and dyn_mode == DYN_GP:
        for i in range(5):
            for j in range(5):
                covs[0, i, j] = cov0[i, j]
    tmp = np.empty((5, 5))
    jac = np.eye(5)  # one Jacobian, rewritten each step (`jacobian_into`)
    for k in range(n):
        x = states[k]
        r = step_state(dyn, gp, scratch, dt, (x[0], x[1], x[2], x[3], x[4]), (controls[k, 0], controls[k, 1]), 1.0)
        for i in range(5):
            states[k + 1, i] = r[i]
        if dyn_mode == DYN_GP:
            step_var[k, 0] = r[7] + noise_v
            step_var[k, 1] = r[8] + noise_w
            jacobian_into(jac, theta, x, controls[k], dt, r[5], r[6], lateral[0], lateral[1])
            _sandwich(jac, covs[k], tmp, covs[k + 1])
            covs[k + 1, 3, 3] += step_var[k, 0]
            covs[k + 1, 4, 4] += step_var[k, 1]
    return states, covs, step_var


@njit(cache=True)
def predict_ahead(
    model: tuple, x0: np.ndarray, cov0: np.ndarray, control: np.ndarray, delay: float, dt: float,
    noise_v: float = 0.0, noise_w: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean state and covariance `delay` seconds after `x0` under the constant `control`, by the model of `model`
    (`ModelBundle.args()`).

    Substeps of at most 10 ms. The GP residual is a change over one planner step `dt`, so a substep of h adds
    h/dt of its mean and of its variance (the residual spread evenly over the step); `noise_v`, `noise_w` as in
    `propagate`. Models without a GP leave the covariance as it is.
    """
    dyn_mode = model.dyn_mode
    theta = model.theta
    lateral = model.lateral
    dyn = dyn_inputs(model, velocity_coefficients(theta, lateral))
    gp = gp_inputs(model)
    scratch = gp_scratch(model)
    n = max(1, int(math.ceil(delay / 0.01)))
    h = delay / n
    frac = h / dt
    x = x0.copy()
    cov = cov0.copy()
    tmp = np.empty((5, 5))
    nxt = np.empty((5, 5))
    jac = np.eye(5)
    u = (control[0], control[1])
    for _ in range(n):
        r = step_state(dyn, gp, scratch, h, (x[0], x[1], x[2], x[3], x[4]), u, frac)
        if dyn_mode == DYN_GP:
            jacobian_into(jac, theta, x, control, h, r[5], r[6], lateral[0], lateral[1])
            _sandwich(jac, cov, tmp, nxt)
            for i in range(5):  # element by element, as in `propagate`
                for j in range(5):
                    cov[i, j] = nxt[i, j]
            cov[3, 3] += frac * (r[7] + noise_v)
            cov[4, 4] += frac * (r[8] + noise_w)
        for i in range(5):
            x[i] = r[i]
    return x, cov
