"""What a terrain estimator publishes (`TerrainEstimate`) and what every estimator is (`EstimatorLike`).

Free of the estimators themselves (and of cvxpy), so the terrain service's cycle can hold one by its protocol.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass
class TerrainEstimate:
    weights: np.ndarray  # (M,) on the simplex
    ok: bool  # False: the weights are the previous ones (see message)
    residual: float  # fit term ||Y - F w||^2 at the returned weights (unnormalised, in (m/s)^2 + (rad/s)^2)
    message: str
    unknown: float = 0.0  # P(the ground is none of the trained ones) (gpmppi.terrain.novelty; 0: not assessed)
    unknown_active: bool = False  # the hysteretic decision on `unknown` (planner caution, events)
    # which channel of the test gave `unknown`: "one-step" (the residual), "free-run" (the response run free: grip);
    # "" while neither has scored a whole window, or without the test
    unknown_channel: str = ""
    # whether the weights name a top ground: False while the evidence has established none (the Bayesian estimator's
    # `first_top: established` before its first identification; the weights are then the posterior as it is, and
    # their argmax is no identification). Every other estimate's top is its weights' argmax
    identified: bool = True


class EstimatorLike(Protocol):
    """A terrain-weight estimator: observes steps, estimates weights over the model's terrains."""

    min_history: int  # steps observed before the first estimate (before: the starting weights, ok False)

    @property
    def weights(self) -> np.ndarray:
        """(M,) the weights of the last estimate (before one: the starting weights)."""
        ...

    def observe(self, state: np.ndarray, command: np.ndarray, next_state: np.ndarray) -> None:
        """Add one step: state (5,) at t, command (2,) applied over [t, t + dt), next_state (5,) at t + dt."""
        ...

    def estimate(self) -> TerrainEstimate: ...

    def __len__(self) -> int: ...
