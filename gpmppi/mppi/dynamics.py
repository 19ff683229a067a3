"""One rollout step of each planner model, the weighted-ensemble GP table, and covariance propagation.

Models (`DYN_*`): the kinematic unicycle; EDD5 of one terrain; the nominal dynamic unicycle
(explicit Euler) plus the weighted GP ensemble residual on the velocities,
mean `sum_i w_i m_i`, variance `sum_i w_i^2 C_i` (C = latent variance).

GP evaluation (`GP_*`): `grid` interpolates a table of [mean_v, mean_w, var_v, var_w] collapsed
from the model's (G, G, G, G, 4M) table with the current weights (`collapse_table`, run only when
the weights change; packed so one interpolation reads 4 cache lines); `exact` evaluates the exact
GP (`gpmppi.gp.exact.exact_point`).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from gpmppi.gp.exact import exact_point
from gpmppi.models.dynamic_unicycle import jacobian
from gpmppi.models.edd5 import edd5_velocity
from gpmppi.mppi.flags import FASTMATH

DYN_UNICYCLE = 0
DYN_EDD5 = 1
DYN_GP = 2
GP_GRID = 0
GP_EXACT = 1


def packed_table_shape(grid_shape: tuple[int, ...]) -> tuple[int, int, int, int, int, int]:
    g0, g1, g2, g3 = grid_shape[:4]
    return (g0, g1, g2 - 1, g3 - 1, 4, 4)


def empty_packed_table(grid_shape: tuple[int, ...]) -> np.ndarray:
    """A float32 packed table whose 64-byte blocks start on cache-line boundaries."""
    shape = packed_table_shape(grid_shape)
    n = int(np.prod(shape))
    buf = np.empty(n + 16, dtype=np.float32)
    off = (-buf.ctypes.data % 64) // 4
    return buf[off : off + n].reshape(shape)


@njit(cache=True, parallel=True)
def collapse_table(table: np.ndarray, weights: np.ndarray, out: np.ndarray) -> None:
    """Model table (G,G,G,G,4M) -> weighted-ensemble table in `out`, packed for interpolation.

    Channels [sum w m_v, sum w m_w, sum w^2 C_v, sum w^2 C_w]. Layout (G, G, G-1, G-1, 4, 4): for
    each cell corner (i0, i1, i2, i3) the 2x2 nodes (i2 + b2, i3 + b3) along the last two axes sit in
    one 64-byte block (q = 2 b2 + b3), so an interpolation touches 4 cache lines instead of ~12.
    """
    g0, g1, g2, g3, c = table.shape
    m = c // 4
    for i0 in prange(g0):
        for i1 in range(g1):
            for j2 in range(g2):
                for j3 in range(g3):
                    mv = 0.0
                    mw = 0.0
                    cv = 0.0
                    cw = 0.0
                    node = table[i0, i1, j2, j3]
                    for t in range(m):
                        wt = weights[t]
                        mv += wt * node[2 * t]
                        mw += wt * node[2 * t + 1]
                        cv += wt * wt * node[2 * m + 2 * t]
                        cw += wt * wt * node[2 * m + 2 * t + 1]
                    # node (j2, j3) is corner (b2, b3) of cells (j2 - b2, j3 - b3)
                    for b2 in range(2):
                        i2 = j2 - b2
                        if i2 < 0 or i2 > g2 - 2:
                            continue
                        for b3 in range(2):
                            i3 = j3 - b3
                            if i3 < 0 or i3 > g3 - 2:
                                continue
                            q = 2 * b2 + b3
                            out[i0, i1, i2, i3, q, 0] = mv
                            out[i0, i1, i2, i3, q, 1] = mw
                            out[i0, i1, i2, i3, q, 2] = cv
                            out[i0, i1, i2, i3, q, 3] = cw


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _axis(x: float, lo: float, inv_step: float, g: int) -> tuple[int, float]:
    t = (x - lo) * inv_step
    if t <= 0.0:
        return 0, 0.0
    if t >= g - 1:
        return g - 2, 1.0
    i = int(t)
    return i, t - i


@njit(cache=True, fastmath=FASTMATH, inline="always")
def interp4(
    packed: np.ndarray, lo: np.ndarray, inv_step: np.ndarray, a0: float, a1: float, a2: float, a3: float
) -> tuple[float, float, float, float]:
    """Multilinear interpolation of the 4 channels of a packed table (clamped at the faces)."""
    i0, f0 = _axis(a0, lo[0], inv_step[0], packed.shape[0])
    i1, f1 = _axis(a1, lo[1], inv_step[1], packed.shape[1])
    i2, f2 = _axis(a2, lo[2], inv_step[2], packed.shape[2] + 1)
    i3, f3 = _axis(a3, lo[3], inv_step[3], packed.shape[3] + 1)
    w23_0 = (1.0 - f2) * (1.0 - f3)
    w23_1 = (1.0 - f2) * f3
    w23_2 = f2 * (1.0 - f3)
    w23_3 = f2 * f3
    c0 = 0.0
    c1 = 0.0
    c2 = 0.0
    c3 = 0.0
    for b0 in range(2):
        w0 = f0 if b0 else 1.0 - f0
        for b1 in range(2):
            w01 = w0 * (f1 if b1 else 1.0 - f1)
            blk = packed[i0 + b0, i1 + b1, i2, i3]
            for ch in range(4):
                v = (w23_0 * blk[0, ch] + w23_1 * blk[1, ch] + w23_2 * blk[2, ch] + w23_3 * blk[3, ch]) * w01
                if ch == 0:
                    c0 += v
                elif ch == 1:
                    c1 += v
                elif ch == 2:
                    c2 += v
                else:
                    c3 += v
    return c0, c1, c2, c3


@njit(cache=True, fastmath=FASTMATH, inline="always")
def gp_residual(
    gp_mode: int, table: np.ndarray, lo: np.ndarray, inv_step: np.ndarray,
    ex_scaled_x: np.ndarray, ex_inv_ls: np.ndarray, ex_outputscale: np.ndarray, ex_alpha: np.ndarray,
    ex_chol: np.ndarray, terrain_w: np.ndarray, work: np.ndarray, gp_in: np.ndarray, gp_mean: np.ndarray,
    gp_var: np.ndarray, v_ref: float, w_ref: float, v: float, w: float,
) -> tuple[float, float, float, float]:
    """Ensemble residual (mean_v, mean_w, var_v, var_w) at GP input [v_ref, w_ref, v, w]."""
    if gp_mode == GP_GRID:
        return interp4(table, lo, inv_step, v_ref, w_ref, v, w)
    gp_in[0] = v_ref
    gp_in[1] = w_ref
    gp_in[2] = v
    gp_in[3] = w
    exact_point(gp_in, ex_scaled_x, ex_inv_ls, ex_outputscale, ex_alpha, ex_chol, work, gp_mean, gp_var, True)
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


@njit(cache=True, fastmath=FASTMATH, inline="always")
def nominal_velocity_step(
    theta: np.ndarray, v: float, w: float, v_ref: float, w_ref: float, dt: float
) -> tuple[float, float]:
    """Explicit-Euler velocity step of the nominal dynamic unicycle (same as `euler_step`)."""
    vdot = (theta[2] / theta[0]) * w * w - (theta[3] / theta[0]) * v + v_ref / theta[0]
    wdot = -(theta[4] / theta[1]) * v * w - (theta[5] / theta[1]) * w + w_ref / theta[1]
    return v + vdot * dt, w + wdot * dt


@njit(cache=True, fastmath=FASTMATH, inline="always")
def step_state(
    dyn_mode: int, dt: float, theta: np.ndarray, edd5_p: np.ndarray,
    gp_mode: int, table: np.ndarray, lo: np.ndarray, inv_step: np.ndarray,
    ex_scaled_x: np.ndarray, ex_inv_ls: np.ndarray, ex_outputscale: np.ndarray, ex_alpha: np.ndarray,
    ex_chol: np.ndarray, terrain_w: np.ndarray, work: np.ndarray, gp_in: np.ndarray, gp_mean: np.ndarray,
    gp_var: np.ndarray, px: float, py: float, yaw: float, v: float, w: float, u0: float, u1: float,
) -> tuple[float, float, float, float, float, float, float]:
    """Next state (5 scalars) and the step's residual variances (var_v, var_w) of the chosen model."""
    cv = 0.0
    cw = 0.0
    if dyn_mode == DYN_GP:
        mv, mw, cv, cw = gp_residual(
            gp_mode, table, lo, inv_step, ex_scaled_x, ex_inv_ls, ex_outputscale, ex_alpha, ex_chol,
            terrain_w, work, gp_in, gp_mean, gp_var, u0, u1, v, w,
        )
        v1, w1 = nominal_velocity_step(theta, v, w, u0, u1, dt)
        # dynamic model: the pose advances with the current velocities (explicit Euler)
        c = np.cos(yaw)
        s = np.sin(yaw)
        return px + v * c * dt, py + v * s * dt, yaw + w * dt, v1 + mv, w1 + mw, cv, cw
    if dyn_mode == DYN_EDD5:
        v1, w1 = edd5_velocity(edd5_p, u0, u1)
    else:
        v1 = u0
        w1 = u1
    # kinematic models: velocities follow the command at once, then the pose advances
    c = np.cos(yaw)
    s = np.sin(yaw)
    return px + v1 * c * dt, py + v1 * s * dt, yaw + w1 * dt, v1, w1, cv, cw


@njit(cache=True)
def propagate(
    x0: np.ndarray, controls: np.ndarray, dt: float, dyn_mode: int, theta: np.ndarray, edd5_p: np.ndarray,
    gp_mode: int, table: np.ndarray, lo: np.ndarray, inv_step: np.ndarray,
    ex_scaled_x: np.ndarray, ex_inv_ls: np.ndarray, ex_outputscale: np.ndarray, ex_alpha: np.ndarray,
    ex_chol: np.ndarray, terrain_w: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean states (N+1, 5), covariances (N+1, 5, 5) and step variances (N, 2) along `controls`.

    GP model: Sigma+ = J Sigma J^T + diag(0, 0, 0, C_v, C_w) with J the nominal Euler Jacobian at
    (x_k, u_k); the mean includes the GP mean residual. Other models carry no uncertainty, so their
    covariances stay zero.
    """
    n = controls.shape[0]
    states = np.zeros((n + 1, 5))
    covs = np.zeros((n + 1, 5, 5))
    step_var = np.zeros((n, 2))
    states[0] = x0
    work = np.empty(ex_alpha.shape[1])
    gp_in = np.empty(4)
    gp_mean = np.empty(ex_alpha.shape[0])
    gp_var = np.empty(ex_alpha.shape[0])
    for k in range(n):
        x = states[k]
        r = step_state(
            dyn_mode, dt, theta, edd5_p, gp_mode, table, lo, inv_step, ex_scaled_x, ex_inv_ls, ex_outputscale,
            ex_alpha, ex_chol, terrain_w, work, gp_in, gp_mean, gp_var, x[0], x[1], x[2], x[3], x[4],
            controls[k, 0], controls[k, 1],
        )
        for i in range(5):
            states[k + 1, i] = r[i]
        step_var[k, 0] = r[5]
        step_var[k, 1] = r[6]
        if dyn_mode == DYN_GP:
            jac = jacobian(theta, x, controls[k], dt)
            covs[k + 1] = jac @ covs[k] @ jac.T
            covs[k + 1, 3, 3] += r[5]
            covs[k + 1, 4, 4] += r[6]
    return states, covs, step_var
