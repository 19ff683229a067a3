"""The nominal dynamic unicycle of the paper.

State `[X, Y, theta, v, omega]`, control `[v_ref, omega_ref]`, parameters theta1..6:

    vdot = (th3/th1) w^2 - (th4/th1) v + v_ref/th1
    wdot = -(th5/th2) v w - (th6/th2) w + w_ref/th2

`nominal_step` is the step used inside MPPI rollouts (`jacobian` its derivative); `velocity_step_exact` integrates the
velocity ODE over dt (RK4 with fine substeps, exact to ~1e-10 for dt = 0.1 s), which is how
the paper's residual targets are defined. All functions are numba-compiled so the planner
kernels can call them.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from gpmppi.models.lateral_slip import lateral_velocity, lateral_velocity_grad

N_STATE = 5
N_CONTROL = 2


@njit(cache=True, inline="always")
def accel(theta: np.ndarray, v: float, w: float, v_ref: float, w_ref: float) -> tuple[float, float]:
    """(vdot, wdot) of the nominal model."""
    vdot = (theta[2] / theta[0]) * w * w - (theta[3] / theta[0]) * v + v_ref / theta[0]
    wdot = -(theta[4] / theta[1]) * v * w - (theta[5] / theta[1]) * w + w_ref / theta[1]
    return vdot, wdot


@njit(cache=True, inline="always")
def wrap_angle(a: float) -> float:
    """Wrap to (-pi, pi]."""
    a = (a + np.pi) % (2.0 * np.pi) - np.pi
    if a == -np.pi:
        a = np.pi
    return a


@njit(cache=True)
def nominal_step(
    theta: np.ndarray, x: np.ndarray, u: np.ndarray, dt: float, mv: float = 0.0, mw: float = 0.0,
    lat_a: float = 0.0, lat_b: float = 0.0,
) -> np.ndarray:
    """One step of the full state as the rollouts take it. Yaw is not wrapped.

    Velocities: explicit Euler of the nominal model plus the step's residual (mv, mw). Pose: the mean of
    the start and end velocities along the heading at mid-step (second order in dt; the pose of an
    explicit-Euler step lags by half a step's change in yaw rate, 0.05 rad for 1 rad/s), plus the sideways
    slide `lateral_velocity(lat_a, lat_b)` at those mean velocities (`gpmppi.models.lateral_slip`).
    """
    vdot, wdot = accel(theta, x[3], x[4], u[0], u[1])
    v1 = x[3] + vdot * dt + mv
    w1 = x[4] + wdot * dt + mw
    vm = 0.5 * (x[3] + v1)
    wm = 0.5 * (x[4] + w1)
    heading = x[2] + 0.5 * wm * dt
    vy = lateral_velocity(lat_a, lat_b, vm, wm)
    c, s = np.cos(heading), np.sin(heading)
    out = np.empty(N_STATE)
    out[0] = x[0] + (vm * c - vy * s) * dt
    out[1] = x[1] + (vm * s + vy * c) * dt
    out[2] = x[2] + wm * dt
    out[3] = v1
    out[4] = w1
    return out


@njit(cache=True)
def jacobian(
    theta: np.ndarray, x: np.ndarray, u: np.ndarray, dt: float, mv: float = 0.0, mw: float = 0.0,
    lat_a: float = 0.0, lat_b: float = 0.0,
) -> np.ndarray:
    """d nominal_step / d x at (x, u) with the residual (mv, mw) held: the 5x5 Jacobian that propagates covariance."""
    J = np.eye(N_STATE)
    jacobian_into(J, theta, x, u, dt, mv, mw, lat_a, lat_b)
    return J


@njit(cache=True)
def jacobian_into(
    J: np.ndarray, theta: np.ndarray, x: np.ndarray, u: np.ndarray, dt: float, mv: float, mw: float, lat_a: float,
    lat_b: float,
) -> None:
    """`jacobian` into `J` (5, 5), which holds the identity's entries where a Jacobian has them (`np.eye(5)` once):
    only the entries that depend on (x, u) are written. The covariance propagation steps through one array rather
    than a new one per step."""
    v, w = x[3], x[4]
    vdot, wdot = accel(theta, v, w, u[0], u[1])
    dv_dv = 1.0 - (theta[3] / theta[0]) * dt
    dv_dw = 2.0 * (theta[2] / theta[0]) * w * dt
    dw_dv = -(theta[4] / theta[1]) * w * dt
    dw_dw = 1.0 - ((theta[4] / theta[1]) * v + theta[5] / theta[1]) * dt
    vm = v + 0.5 * (vdot * dt + mv)
    wm = w + 0.5 * (wdot * dt + mw)
    # d(vm, wm) / d(v, w)
    vm_v, vm_w = 0.5 * (1.0 + dv_dv), 0.5 * dv_dw
    wm_v, wm_w = 0.5 * dw_dv, 0.5 * (1.0 + dw_dw)
    heading = x[2] + 0.5 * wm * dt
    c, s = np.cos(heading), np.sin(heading)
    vy = lateral_velocity(lat_a, lat_b, vm, wm)
    vy_vm, vy_wm = lateral_velocity_grad(lat_a, lat_b, vm, wm)
    # d vy / d(v, w) through the mean velocities; d heading / d(v, w) = 0.5 dt d wm / d(v, w)
    vy_v, vy_w = vy_vm * vm_v + vy_wm * wm_v, vy_vm * vm_w + vy_wm * wm_w
    h_v, h_w = 0.5 * dt * wm_v, 0.5 * dt * wm_w
    fx = vm * c - vy * s  # world-frame velocity of the step
    fy = vm * s + vy * c
    J[0, 2] = -fy * dt
    J[0, 3] = (vm_v * c - vy_v * s - fy * h_v) * dt
    J[0, 4] = (vm_w * c - vy_w * s - fy * h_w) * dt
    J[1, 2] = fx * dt
    J[1, 3] = (vm_v * s + vy_v * c + fx * h_v) * dt
    J[1, 4] = (vm_w * s + vy_w * c + fx * h_w) * dt
    J[2, 3] = wm_v * dt
    J[2, 4] = wm_w * dt
    J[3, 3] = dv_dv
    J[3, 4] = dv_dw
    J[4, 3] = dw_dv
    J[4, 4] = dw_dw


@njit(cache=True)
def velocity_step_exact(
    theta: np.ndarray, v: np.ndarray, w: np.ndarray, v_ref: np.ndarray, w_ref: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Next (v, omega) after dt under constant command, integrating the ODE (RK4, 50 substeps).

    Arrays of equal length in, arrays out. This defines the one-step residual targets:
    residual = measured next velocity - velocity_step_exact(...).
    """
    n = v.shape[0]
    v_out = np.empty(n)
    w_out = np.empty(n)
    substeps = 50
    h = dt / substeps
    for i in range(n):
        a, b = v[i], w[i]
        for _ in range(substeps):
            k1v, k1w = accel(theta, a, b, v_ref[i], w_ref[i])
            k2v, k2w = accel(theta, a + 0.5 * h * k1v, b + 0.5 * h * k1w, v_ref[i], w_ref[i])
            k3v, k3w = accel(theta, a + 0.5 * h * k2v, b + 0.5 * h * k2w, v_ref[i], w_ref[i])
            k4v, k4w = accel(theta, a + h * k3v, b + h * k3w, v_ref[i], w_ref[i])
            a += h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
            b += h / 6.0 * (k1w + 2 * k2w + 2 * k3w + k4w)
        v_out[i] = a
        w_out[i] = b
    return v_out, w_out
