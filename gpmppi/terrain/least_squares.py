"""Online terrain-weight estimator: which mixture of the trained terrains explains the recent motion.

Over a history of H steps (state, command, next state) the measured one-step velocity residual
`Y = next velocity - velocity_step_exact(...)` is regressed on the terrains' GP mean residuals
`F[:, i]` at the same GP inputs:

    min_w (1/n) (||Y_v - F_v w||^2 / s_v^2 + ||Y_w - F_w w||^2 / s_w^2) + gamma ||w - w_prev||_1,
    0 <= w <= 1,  sum w = 1

with n the steps in the history and s_v^2, s_w^2 the model's likelihood noise variances of the v
and omega tasks (mean over the terrains). The fit is thus the mean squared residual in units of
the noise the GP was trained with: about 1 per step at the right weights, whatever the robot's
speed or the history length, so gamma (the price of moving the weights, in those units) means the
same on every model. Unnormalised, the fit of velocity residuals of a few mm/s per step is ~1e-3
and any gamma of a useful size pins the weights where they started.

The cvxpy problem is built once with Parameters (it is DPP, so re-solving only refills numbers)
and re-solved warm each cycle. Histories shorter than H fill the unused rows with zeros, which
add nothing to the fit. When the history is too short or the solver fails, the previous weights
are kept and the estimate says why.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from gpmppi.gp.exact import ExactPredictor
from gpmppi.gp.model_file import GPModel
from gpmppi.models.dynamic_unicycle import velocity_step_exact
from gpmppi.terrain.estimate import TerrainEstimate

__all__ = ["TerrainEstimator", "checked_vector"]


def checked_vector(name: str, value: np.ndarray, n: int) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64).reshape(-1)
    if a.shape != (n,):
        raise ValueError(f"{name} must have {n} numbers, got shape {np.shape(value)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a.tolist()}")
    return a


class TerrainEstimator:
    """Keeps the last `history` steps and solves the weight problem on demand."""

    def __init__(self, model: GPModel, history: int = 20, gamma: float = 0.1, min_history: int = 3) -> None:
        if history < 1:
            raise ValueError(f"history must be >= 1 step, got {history}")
        if not (np.isfinite(gamma) and gamma >= 0):
            raise ValueError(f"gamma must be >= 0, got {gamma}")
        if not 1 <= min_history <= history:
            raise ValueError(f"min_history must be in [1, history={history}], got {min_history}")
        self.model = model
        self.history = history
        self.gamma = float(gamma)
        self.min_history = min_history
        self._m = len(model.terrains)
        self._predictor = ExactPredictor(model)
        noise = np.asarray(model.noise, dtype=np.float64).reshape(-1)
        # noise std of the v and omega residuals: the unit of the fit (floored so a noiseless model stays finite)
        self._noise_std = np.sqrt(np.maximum([noise[0::2].mean(), noise[1::2].mean()], 1e-12))
        self._rows: deque[tuple[float, float, np.ndarray, np.ndarray]] = deque(maxlen=history)
        # here, not at the top: cvxpy (with scipy.sparse and scipy.stats) is ~1 s of the terrain service's start, and
        # only this estimator (method 'paper', not the default) solves a convex problem
        import cvxpy as cp

        m, h = self._m, history
        self._w = cp.Variable(m, name="w")
        self._f_v = cp.Parameter((h, m), name="F_v")
        self._f_w = cp.Parameter((h, m), name="F_w")
        self._y_v = cp.Parameter(h, name="Y_v")
        self._y_w = cp.Parameter(h, name="Y_w")
        self._w_prev = cp.Parameter(m, name="w_prev")
        self._fit = cp.sum_squares(self._y_v - self._f_v @ self._w) + cp.sum_squares(self._y_w - self._f_w @ self._w)
        objective = self._fit + self.gamma * cp.norm1(self._w - self._w_prev)
        constraints = [self._w >= 0, self._w <= 1, cp.sum(self._w) == 1]
        self._problem = cp.Problem(cp.Minimize(objective), constraints)
        if not self._problem.is_dpp():  # re-solves would re-canonicalise from scratch
            raise RuntimeError("terrain weight problem is not DPP; parameters would not be reused")
        self.reset()

    def reset(self, weights: np.ndarray | None = None) -> None:
        """Forget the history; start from `weights` (default uniform)."""
        self._rows.clear()
        w = np.full(self._m, 1.0 / self._m) if weights is None else checked_vector("weights", weights, self._m)
        if np.any(w < 0) or abs(w.sum() - 1.0) > 1e-6:
            raise ValueError(f"weights must lie on the simplex, got {w.tolist()}")
        self._weights = w.copy()

    @property
    def weights(self) -> np.ndarray:
        return self._weights.copy()

    def __len__(self) -> int:
        return len(self._rows)

    def observe(self, state: np.ndarray, command: np.ndarray, next_state: np.ndarray) -> None:
        """Add one step: state (5,) at t, command (2,) applied over [t, t + dt), next_state (5,) at t + dt."""
        x = checked_vector("state", state, 5)
        u = checked_vector("command", command, 2)
        x1 = checked_vector("next_state", next_state, 5)
        theta = self.model.theta
        v_nom, w_nom = velocity_step_exact(
            theta, x[3:4].copy(), x[4:5].copy(), u[0:1].copy(), u[1:2].copy(), self.model.dt
        )
        mean, _ = self._predictor.predict(np.array([[u[0], u[1], x[3], x[4]]]), with_var=False)
        self._rows.append((x1[3] - v_nom[0], x1[4] - w_nom[0], mean[0, 0::2].copy(), mean[0, 1::2].copy()))

    def estimate(self) -> TerrainEstimate:
        """Solve the weight problem over the current history (warm-started)."""
        n = len(self._rows)
        if n < self.min_history:
            return TerrainEstimate(self.weights, False, float("nan"),
                                   f"history too short ({n} of {self.min_history} steps); keeping previous weights")
        h, m = self.history, self._m
        y_v = np.zeros(h)
        y_w = np.zeros(h)
        f_v = np.zeros((h, m))
        f_w = np.zeros((h, m))
        for i, (yv, yw, fv, fw) in enumerate(self._rows):
            y_v[i], y_w[i], f_v[i], f_w[i] = yv, yw, fv, fw
        # scaling the data (not the expression) keeps the problem DPP: the fit is the mean squared residual
        # over the n filled rows in units of the model's noise std
        scale_v = 1.0 / (self._noise_std[0] * np.sqrt(n))
        scale_w = 1.0 / (self._noise_std[1] * np.sqrt(n))
        self._y_v.value, self._f_v.value = y_v * scale_v, f_v * scale_v
        self._y_w.value, self._f_w.value = y_w * scale_w, f_w * scale_w
        self._w_prev.value = self._weights
        import cvxpy as cp  # imported by __init__ already

        try:
            self._problem.solve(solver=cp.CLARABEL)
            status = self._problem.status
        except cp.error.SolverError as e:
            status = f"solver error: {e}"
        w = self._w.value
        if status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or w is None or not np.all(np.isfinite(w)):
            return TerrainEstimate(self.weights, False, float("nan"),
                                   f"weight problem not solved ({status}); keeping previous weights")
        w = np.clip(np.asarray(w, dtype=np.float64), 0.0, 1.0)
        w /= w.sum()
        self._weights = w
        fit = float(np.sum((y_v - f_v @ w) ** 2) + np.sum((y_w - f_w @ w) ** 2))
        return TerrainEstimate(w.copy(), True, fit, f"solved over {n} steps ({status})")
