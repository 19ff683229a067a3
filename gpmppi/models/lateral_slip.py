"""Lateral slip of a skid-steer base in turns: the body-frame sideways velocity the unicycle models leave out.

A skid-steer robot turning at speed slides outwards: the lateral wheel forces that carry the centripetal
acceleration `v omega` need a sideways slip velocity. The planner's GP corrects only the forward speed and
yaw rate, so without this term every rollout of a fast turn ends on the inside of where the robot goes
(on the physics plant's tile, 0.13 m/s sideways at 1.5 m/s and 1 rad/s).

Per terrain, two coefficients fitted by least squares from logged poses:

    v_y = a v omega + b v omega |omega|

The pair of features fits the physics plant's steady turns (v 0.25-2 m/s, |omega| 0.3-2 rad/s, 4 s each)
on asphalt, grass and sand to 1.5-2.7 mm/s rms (of 36-48 mm/s rms), and on tile, where the slide saturates
in the tightest fast turns, to 65 mm/s of 238; one feature alone (`v omega`) left 15-47% of the rms.
The planner blends the coefficients by the terrain weights (the model is linear in them), as it blends
the GP means.
"""

from __future__ import annotations

import numpy as np
from numba import njit

N_LATERAL = 2  # coefficients per terrain: (a, b)


@njit(cache=True, inline="always")
def lateral_velocity(a: float, b: float, v: float, w: float) -> float:
    """Body-frame lateral velocity [m/s] (positive to the left) at forward speed v and yaw rate w."""
    return (a + b * abs(w)) * v * w


@njit(cache=True, inline="always")
def lateral_velocity_grad(a: float, b: float, v: float, w: float) -> tuple[float, float]:
    """(d v_y / d v, d v_y / d w) of `lateral_velocity`."""
    aw = abs(w)
    return (a + b * aw) * w, (a + 2.0 * b * aw) * v


def body_lateral_velocity(
    x: np.ndarray, y: np.ndarray, yaw: np.ndarray, dt: float, seg: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Sideways velocity of each step between consecutive poses of a segment, in the mid-step body frame.

    Returns (index of the step's first sample, v_y) for the steps whose two poses share a segment id.
    """
    x, y, yaw = (np.asarray(a, dtype=np.float64) for a in (x, y, yaw))
    n = len(x)
    if not (len(y) == n and len(yaw) == n):
        raise ValueError("x, y and yaw must have the same length")
    same = np.ones(max(n - 1, 0), dtype=bool) if seg is None else np.asarray(seg)[1:] == np.asarray(seg)[:-1]
    i = np.flatnonzero(same)
    dyaw = np.angle(np.exp(1j * (yaw[i + 1] - yaw[i])))  # wrapped step of yaw
    mid = yaw[i] + 0.5 * dyaw
    vy = (-np.sin(mid) * (x[i + 1] - x[i]) + np.cos(mid) * (y[i + 1] - y[i])) / dt
    return i, vy


def lateral_features(v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The regression matrix (n, 2) of `lateral_velocity`: columns v omega and v omega |omega|."""
    v = np.asarray(v, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)
    return np.column_stack([v * w, v * w * np.abs(w)])


def fit_lateral_slip(v: np.ndarray, w: np.ndarray, vy: np.ndarray, min_turning: int = 50) -> np.ndarray:
    """Least-squares (a, b) of `lateral_velocity` from mid-step speeds, yaw rates and sideways velocities.

    Data with fewer than `min_turning` samples that turn at speed (|v omega| > 0.1 m/s^2) cannot tell a
    slide from noise: the fit is (0, 0) then, the planner's model without lateral slip.
    """
    A = lateral_features(v, w)
    vy = np.asarray(vy, dtype=np.float64)
    ok = np.all(np.isfinite(A), axis=1) & np.isfinite(vy)
    A, vy = A[ok], vy[ok]
    if int(np.sum(np.abs(A[:, 0]) > 0.1)) < min_turning:
        return np.zeros(N_LATERAL)
    coef, *_ = np.linalg.lstsq(A, vy, rcond=None)
    return coef.astype(np.float64)
