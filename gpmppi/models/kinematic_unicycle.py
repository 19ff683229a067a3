"""The kinematic unicycle baseline: velocities follow the command instantly."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def kinematic_step(x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """State `[X, Y, theta, v, omega]`; v and omega are set to the command, then pose advances."""
    out = np.empty(5)
    out[3] = u[0]
    out[4] = u[1]
    out[0] = x[0] + u[0] * np.cos(x[2]) * dt
    out[1] = x[1] + u[0] * np.sin(x[2]) * dt
    out[2] = x[2] + u[1] * dt
    return out
