"""One rollout step of each planner model, the weighted-ensemble GP table, and covariance propagation.

Models (`DYN_*`): the kinematic unicycle; EDD5 of one terrain; the nominal dynamic unicycle
(explicit Euler) plus the weighted GP ensemble residual on the velocities,
mean `sum_i w_i m_i`, variance `sum_i w_i^2 C_i` (C = latent variance).

GP evaluation (`GP_*`): `grid` interpolates (simplex or multilinear) a table of
[mean_v, mean_w, var_v, var_w] collapsed from the model's (G, G, G, G, 4M) table with the current
weights (`collapse_table`, run only when the weights change); `exact` evaluates the exact GP
(`gpmppi.gp.exact.exact_tasks`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from gpmppi.gp.exact import exact_tasks
from gpmppi.gp.grid_interp import grid_cell
from gpmppi.models.dynamic_unicycle import jacobian
from gpmppi.models.edd5 import edd5_velocity
from gpmppi.mppi.flags import FASTMATH, fmax, fmin

DYN_UNICYCLE = 0
DYN_EDD5 = 1
DYN_GP = 2
GP_GRID = 0  # grid table, multilinear interpolation (16 nodes)
GP_EXACT = 1  # exact GP
GP_SIMPLEX = 2  # grid table, simplex interpolation (5 nodes)


TABLE_AXES = np.array([2, 3, 0, 1])  # collapsed table axes in terms of the GP input [v_ref, omega_ref, v, omega]


def rollout_order(table: np.ndarray) -> np.ndarray:
    """The model's (G,G,G,G,4M) grid table with its axes in `TABLE_AXES` order, float32, contiguous.

    A rollout's velocities change slowly from step to step while its noisy commands jump, so with
    the velocity axes outermost consecutive lookups of one sample stay within a few planes of the
    table. Done once per planner: collapsing from this order reads and writes in one stream
    (collapsing with the transposition inside wrote with a large stride and took 2x as long).
    """
    return np.ascontiguousarray(np.transpose(table, (2, 3, 0, 1, 4)), dtype=np.float32)


def collapse_table(
    table: np.ndarray, weights: np.ndarray, noise: tuple[float, float] = (0.0, 0.0), ordered: bool = False
) -> np.ndarray:
    """(G,G,G,G,4M) table -> (G,G,G,G,4) float32 [sum w m_v, sum w m_w, sum w^2 C_v + n_v, sum w^2 C_w + n_w].

    `table` is the model's grid table, or (`ordered=True`) its `rollout_order` copy; the output's axes
    are in `TABLE_AXES` order either way. `noise` (n_v, n_w) is added to the two variance channels.
    """
    src = table if ordered else rollout_order(table)
    # allocated by numpy, which asks the kernel for huge pages on large arrays: the rollouts read
    # this table at random, and huge pages mean fewer TLB misses
    out = np.empty(src.shape[:4] + (4,), dtype=np.float32)
    _collapse_into(src, np.ascontiguousarray(weights, dtype=np.float64), float(noise[0]), float(noise[1]), out)
    return out


@njit(cache=True, parallel=True)
def _collapse_into(table: np.ndarray, weights: np.ndarray, noise_v: float, noise_w: float, out: np.ndarray) -> None:
    g0, g1, g2, g3, c = table.shape
    m = c // 4
    for i0 in prange(g0):
        for i1 in range(g1):
            for i2 in range(g2):
                for i3 in range(g3):
                    node = table[i0, i1, i2, i3]
                    mv = 0.0
                    mw = 0.0
                    cv = noise_v
                    cw = noise_w
                    for t in range(m):
                        wt = weights[t]
                        mv += wt * node[2 * t]
                        mw += wt * node[2 * t + 1]
                        cv += wt * wt * node[2 * m + 2 * t]
                        cw += wt * wt * node[2 * m + 2 * t + 1]
                    out[i0, i1, i2, i3, 0] = mv
                    out[i0, i1, i2, i3, 1] = mw
                    out[i0, i1, i2, i3, 2] = cv
                    out[i0, i1, i2, i3, 3] = cw


@njit(cache=True, fastmath=FASTMATH, inline="always")
def interp4(
    table: np.ndarray, dims: np.ndarray, lo: np.ndarray, inv_step: np.ndarray, a0: float, a1: float, a2: float,
    a3: float,
) -> tuple[float, float, float, float]:
    """Multilinear interpolation of a (G0*G1*G2*G3, 4) float32 table with grid `dims` (clamped at the faces).

    Flat node indices and single-precision accumulation (no float64 conversion of the 64 loaded
    values); a (nodes, 4) table measured faster here than a 1-D one.
    """
    i0, f0 = grid_cell(a0, lo[0], inv_step[0], dims[0])
    i1, f1 = grid_cell(a1, lo[1], inv_step[1], dims[1])
    i2, f2 = grid_cell(a2, lo[2], inv_step[2], dims[2])
    i3, f3 = grid_cell(a3, lo[3], inv_step[3], dims[3])
    s2 = dims[3]
    s1 = dims[2] * s2
    s0 = dims[1] * s1
    base = i0 * s0 + i1 * s1 + i2 * s2 + i3
    g0 = np.float32(f0)
    g1 = np.float32(f1)
    g2 = np.float32(f2)
    g3 = np.float32(f3)
    one = np.float32(1.0)
    e0 = one - g0
    e1 = one - g1
    e2 = one - g2
    e3 = one - g3
    c0 = np.float32(0.0)
    c1 = np.float32(0.0)
    c2 = np.float32(0.0)
    c3 = np.float32(0.0)
    # 8 pairs of nodes adjacent along the last axis
    for b in range(8):
        b0 = b >> 2
        b1 = (b >> 1) & 1
        b2 = b & 1
        w = (g0 if b0 else e0) * (g1 if b1 else e1) * (g2 if b2 else e2)
        lo_w = w * e3
        hi_w = w * g3
        n = base + b0 * s0 + b1 * s1 + b2 * s2
        c0 += lo_w * table[n, 0] + hi_w * table[n + 1, 0]
        c1 += lo_w * table[n, 1] + hi_w * table[n + 1, 1]
        c2 += lo_w * table[n, 2] + hi_w * table[n + 1, 2]
        c3 += lo_w * table[n, 3] + hi_w * table[n + 1, 3]
    return float(c0), float(c1), float(c2), float(c3)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _cswap(fa: float, sa: int, fb: float, sb: int) -> tuple[float, int, float, int]:
    """Order two (fraction, stride) pairs by descending fraction.

    Written as selects, not a branch: the fractions are random, a branch would mispredict half the time.
    """
    swap = fb > fa
    # selects, not max/min: numba's CUDA target cannot compile float max/min
    return fmax(fa, fb), sb if swap else sa, fmin(fa, fb), sa if swap else sb


@njit(cache=True, fastmath=FASTMATH, inline="always")
def simplex_nodes(
    dims: np.ndarray, lo: np.ndarray, inv_step: np.ndarray, a0: float, a1: float, a2: float, a3: float
) -> tuple[int, int, int, int, int, float, float, float, float, float]:
    """The 5 node indices and barycentric weights of the Kuhn simplex holding the point (see `interp4_simplex`)."""
    i0, f0 = grid_cell(a0, lo[0], inv_step[0], dims[0])
    i1, f1 = grid_cell(a1, lo[1], inv_step[1], dims[1])
    i2, f2 = grid_cell(a2, lo[2], inv_step[2], dims[2])
    i3, f3 = grid_cell(a3, lo[3], inv_step[3], dims[3])
    s3 = 1
    s2 = dims[3]
    s1 = dims[2] * s2
    s0 = dims[1] * s1
    n0 = i0 * s0 + i1 * s1 + i2 * s2 + i3
    # sorting network for 4 elements (5 compare-exchanges), descending by fraction
    f0, s0, f1, s1 = _cswap(f0, s0, f1, s1)
    f2, s2, f3, s3 = _cswap(f2, s2, f3, s3)
    f0, s0, f2, s2 = _cswap(f0, s0, f2, s2)
    f1, s1, f3, s3 = _cswap(f1, s1, f3, s3)
    f1, s1, f2, s2 = _cswap(f1, s1, f2, s2)
    n1 = n0 + s0
    n2 = n1 + s1
    n3 = n2 + s2
    n4 = n3 + s3
    return n0, n1, n2, n3, n4, 1.0 - f0, f0 - f1, f1 - f2, f2 - f3, f3


@njit(cache=True, fastmath=FASTMATH, inline="always")
def interp4_simplex(
    table: np.ndarray, dims: np.ndarray, lo: np.ndarray, inv_step: np.ndarray, a0: float, a1: float, a2: float,
    a3: float,
) -> tuple[float, float, float, float]:
    """Simplex (Kuhn / Freudenthal) interpolation of the same (nodes, 4) table: 5 nodes instead of 16.

    The cell is split into 24 simplices by the order of the fractional coordinates; the value is
    the barycentric blend of the simplex's 5 vertices. Like multilinear interpolation it is exact
    at the nodes, continuous, and second-order accurate, but reads 5 nodes instead of 16: on a
    table larger than the caches that is the difference (it is memory-bound).
    """
    n0, n1, n2, n3, n4, w0, w1, w2, w3, w4 = simplex_nodes(dims, lo, inv_step, a0, a1, a2, a3)
    g0 = np.float32(w0)
    g1 = np.float32(w1)
    g2 = np.float32(w2)
    g3 = np.float32(w3)
    g4 = np.float32(w4)
    c0 = g0 * table[n0, 0] + g1 * table[n1, 0] + g2 * table[n2, 0] + g3 * table[n3, 0] + g4 * table[n4, 0]
    c1 = g0 * table[n0, 1] + g1 * table[n1, 1] + g2 * table[n2, 1] + g3 * table[n3, 1] + g4 * table[n4, 1]
    c2 = g0 * table[n0, 2] + g1 * table[n1, 2] + g2 * table[n2, 2] + g3 * table[n3, 2] + g4 * table[n4, 2]
    c3 = g0 * table[n0, 3] + g1 * table[n1, 3] + g2 * table[n2, 3] + g3 * table[n3, 3] + g4 * table[n4, 3]
    return float(c0), float(c1), float(c2), float(c3)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def gp_residual(
    gp_mode: int, table: np.ndarray, dims: np.ndarray, lo: np.ndarray, inv_step: np.ndarray,
    ex_scaled_x: np.ndarray, ex_inv_ls: np.ndarray, ex_outputscale: np.ndarray, ex_alpha: np.ndarray,
    ex_chol: np.ndarray, terrain_w: np.ndarray, work: np.ndarray, gp_mean: np.ndarray, gp_var: np.ndarray,
    v_ref: float, w_ref: float, v: float, w: float,
) -> tuple[float, float, float, float]:
    """Ensemble residual (mean_v, mean_w, var_v, var_w) at GP input [v_ref, w_ref, v, w].

    Grid mode: `table`, `lo`, `inv_step` are in the collapsed table's axis order (`TABLE_AXES`).
    """
    if gp_mode == GP_SIMPLEX:
        return interp4_simplex(table, dims, lo, inv_step, v, w, v_ref, w_ref)
    if gp_mode == GP_GRID:
        return interp4(table, dims, lo, inv_step, v, w, v_ref, w_ref)
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
def velocity_coefficients(theta: np.ndarray) -> np.ndarray:
    """[th3/th1, th4/th1, 1/th1, th5/th2, th6/th2, 1/th2]: divisions done once, not at every sample-step."""
    return np.array([theta[2] / theta[0], theta[3] / theta[0], 1.0 / theta[0],
                     theta[4] / theta[1], theta[5] / theta[1], 1.0 / theta[1]])


@njit(cache=True, fastmath=FASTMATH, inline="always")
def nominal_velocity_step(
    coef: np.ndarray, v: float, w: float, v_ref: float, w_ref: float, dt: float
) -> tuple[float, float]:
    """Explicit-Euler velocity step of the nominal dynamic unicycle (as `euler_step`); `velocity_coefficients`."""
    vdot = coef[0] * w * w - coef[1] * v + v_ref * coef[2]
    wdot = -coef[3] * v * w - coef[4] * w + w_ref * coef[5]
    return v + vdot * dt, w + wdot * dt


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _cos_sin(yaw: float) -> tuple[float, float]:
    """cos and sin in single precision (3x faster; 1e-7 relative is far below the model's errors)."""
    a = np.float32(yaw)
    return float(math.cos(a)), float(math.sin(a))


@njit(cache=True, fastmath=FASTMATH, inline="always")
def advance(
    dyn_mode: int, dt: float, coef: np.ndarray, edd5_p: np.ndarray, px: float, py: float, yaw: float, v: float,
    w: float, u0: float, u1: float, mv: float, mw: float,
) -> tuple[float, float, float, float, float]:
    """Next state (5 scalars) of the chosen model; GP model: (mv, mw) is the step's residual mean.

    `coef` = `velocity_coefficients(theta)`.
    """
    c, s = _cos_sin(yaw)
    if dyn_mode == DYN_GP:
        v1, w1 = nominal_velocity_step(coef, v, w, u0, u1, dt)
        # dynamic model: the pose advances with the current velocities (explicit Euler)
        return px + v * c * dt, py + v * s * dt, yaw + w * dt, v1 + mv, w1 + mw
    if dyn_mode == DYN_EDD5:
        v1, w1 = edd5_velocity(edd5_p, u0, u1)
    else:
        v1 = u0
        w1 = u1
    # kinematic models: velocities follow the command at once, then the pose advances
    return px + v1 * c * dt, py + v1 * s * dt, yaw + w1 * dt, v1, w1


@njit(cache=True, fastmath=FASTMATH, inline="always")
def step_state(
    dyn_mode: int, dt: float, coef: np.ndarray, edd5_p: np.ndarray,
    gp_mode: int, table: np.ndarray, dims: np.ndarray, lo: np.ndarray, inv_step: np.ndarray,
    ex_scaled_x: np.ndarray, ex_inv_ls: np.ndarray, ex_outputscale: np.ndarray, ex_alpha: np.ndarray,
    ex_chol: np.ndarray, terrain_w: np.ndarray, work: np.ndarray, gp_mean: np.ndarray, gp_var: np.ndarray,
    px: float, py: float, yaw: float, v: float, w: float, u0: float, u1: float,
) -> tuple[float, float, float, float, float, float, float]:
    """Next state (5 scalars) and the step's residual variances (var_v, var_w) of the chosen model."""
    mv = 0.0
    mw = 0.0
    cv = 0.0
    cw = 0.0
    if dyn_mode == DYN_GP:
        mv, mw, cv, cw = gp_residual(
            gp_mode, table, dims, lo, inv_step, ex_scaled_x, ex_inv_ls, ex_outputscale, ex_alpha, ex_chol,
            terrain_w, work, gp_mean, gp_var, u0, u1, v, w,
        )
    px, py, yaw, v, w = advance(dyn_mode, dt, coef, edd5_p, px, py, yaw, v, w, u0, u1, mv, mw)
    return px, py, yaw, v, w, cv, cw


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
    x0: np.ndarray, controls: np.ndarray, dt: float, dyn_mode: int, theta: np.ndarray, edd5_p: np.ndarray,
    gp_mode: int, table: np.ndarray, dims: np.ndarray, lo: np.ndarray, inv_step: np.ndarray,
    ex_scaled_x: np.ndarray, ex_inv_ls: np.ndarray, ex_outputscale: np.ndarray, ex_alpha: np.ndarray,
    ex_chol: np.ndarray, terrain_w: np.ndarray, noise_v: float = 0.0, noise_w: float = 0.0,
    cov0: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean states (N+1, 5), covariances (N+1, 5, 5) and step variances (N, 2) along `controls`.

    `cov0` (5, 5) is the covariance of the start state (the state estimate's), zero when None.

    GP model: Sigma+ = J Sigma J^T + diag(0, 0, 0, C_v + noise_v, C_w + noise_w) with J the nominal
    Euler Jacobian at (x_k, u_k) and C the ensemble's latent variance; `noise_v`, `noise_w` are the
    ensemble's likelihood noise `sum_i w_i^2 noise_i` (with it the added term is the GP's predictive
    variance of the next velocity, which is what the data scatter by). The mean includes the GP mean
    residual. Other models carry no uncertainty, so their covariances stay zero. The returned step
    variances are the predictive ones too.
    """
    n = controls.shape[0]
    states = np.zeros((n + 1, 5))
    covs = np.zeros((n + 1, 5, 5))
    step_var = np.zeros((n, 2))
    states[0] = x0
    if cov0 is not None and dyn_mode == DYN_GP:
        covs[0] = cov0
    work = np.empty(ex_alpha.shape[1])
    gp_mean = np.empty(ex_alpha.shape[0])
    gp_var = np.empty(ex_alpha.shape[0])
    tmp = np.empty((5, 5))
    coef = velocity_coefficients(theta)
    for k in range(n):
        x = states[k]
        r = step_state(
            dyn_mode, dt, coef, edd5_p, gp_mode, table, dims, lo, inv_step, ex_scaled_x, ex_inv_ls, ex_outputscale,
            ex_alpha, ex_chol, terrain_w, work, gp_mean, gp_var, x[0], x[1], x[2], x[3], x[4],
            controls[k, 0], controls[k, 1],
        )
        for i in range(5):
            states[k + 1, i] = r[i]
        if dyn_mode == DYN_GP:
            step_var[k, 0] = r[5] + noise_v
            step_var[k, 1] = r[6] + noise_w
            jac = jacobian(theta, x, controls[k], dt)
            _sandwich(jac, covs[k], tmp, covs[k + 1])
            covs[k + 1, 3, 3] += step_var[k, 0]
            covs[k + 1, 4, 4] += step_var[k, 1]
    return states, covs, step_var
