"""The nominal dynamic unicycle of the paper.

State `[X, Y, theta, v, omega]`, control `[v_ref, omega_ref]`, parameters theta1..6:

    vdot = (th3/th1) w^2 - (th4/th1) v + v_ref/th1
    wdot = -(th5/th2) v w - (th6/th2) w + w_ref/th2

`euler_step` is the step used inside MPPI rollouts; `velocity_step_exact` integrates the
velocity ODE over dt (RK4 with fine substeps, exact to ~1e-10 for dt = 0.1 s), which is how
the paper's residual targets are defined. All functions are numba-compiled so the planner
kernels can call them.
"""

from __future__ import annotations

import numpy as np
from numba import njit

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
def euler_step(theta: np.ndarray, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """One explicit-Euler step of the full state (as the rollouts do). Yaw is not wrapped."""
    vdot, wdot = accel(theta, x[3], x[4], u[0], u[1])
    out = np.empty(N_STATE)
    out[0] = x[0] + x[3] * np.cos(x[2]) * dt
    out[1] = x[1] + x[3] * np.sin(x[2]) * dt
    out[2] = x[2] + x[4] * dt
    out[3] = x[3] + vdot * dt
    out[4] = x[4] + wdot * dt
    return out


@njit(cache=True)
def jacobian(theta: np.ndarray, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """d euler_step / d x at (x, u): the 5x5 Jacobian used to propagate covariance."""
    v, w, th = x[3], x[4], x[2]
    J = np.eye(N_STATE)
    J[0, 2] = -v * np.sin(th) * dt
    J[0, 3] = np.cos(th) * dt
    J[1, 2] = v * np.cos(th) * dt
    J[1, 3] = np.sin(th) * dt
    J[2, 4] = dt
    J[3, 3] = 1.0 - (theta[3] / theta[0]) * dt
    J[3, 4] = 2.0 * (theta[2] / theta[0]) * w * dt
    J[4, 3] = -(theta[4] / theta[1]) * w * dt
    J[4, 4] = 1.0 - ((theta[4] / theta[1]) * v + theta[5] / theta[1]) * dt
    return J


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
