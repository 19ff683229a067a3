"""EDD5: the extended differential-drive kinematic model with five parameters per terrain.

Parameters `[alpha_r, alpha_l, x_v, y_r, y_l]`. Wheel speeds from the command
`w_{r,l} = (v +- 0.5 omega b) / r`, then

    v     = r / (y_l - y_r) * (-y_r alpha_l w_l + y_l alpha_r w_r)
    omega = r / (y_l - y_r) * (-alpha_l w_l + alpha_r w_r)

(`x_v`, the ICR's longitudinal offset, gives the lateral slip velocity and does not enter
the forward velocity or yaw rate.)
"""

from __future__ import annotations

import numpy as np
from numba import njit

TRACK_B = 0.377  # [m] Jackal track width used by the paper's EDD5 fit
WHEEL_R = 0.09  # [m] wheel radius used by the paper's EDD5 fit


@njit(cache=True, inline="always")
def edd5_velocity(p: np.ndarray, v_ref: float, w_ref: float) -> tuple[float, float]:
    """(v, omega) the EDD5 model predicts for command (v_ref, w_ref)."""
    w_r = (v_ref + 0.5 * w_ref * TRACK_B) / WHEEL_R
    w_l = (v_ref - 0.5 * w_ref * TRACK_B) / WHEEL_R
    k = WHEEL_R / (p[4] - p[3])
    v = k * (-p[3] * p[1] * w_l + p[4] * p[0] * w_r)
    w = k * (-p[1] * w_l + p[0] * w_r)
    return v, w


@njit(cache=True)
def edd5_step(p: np.ndarray, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """State `[X, Y, theta, v, omega]`: velocities from EDD5, then the pose advances."""
    v, w = edd5_velocity(p, u[0], u[1])
    out = np.empty(5)
    out[3] = v
    out[4] = w
    out[0] = x[0] + v * np.cos(x[2]) * dt
    out[1] = x[1] + v * np.sin(x[2]) * dt
    out[2] = x[2] + w * dt
    return out
