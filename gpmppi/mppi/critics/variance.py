"""Variance critic: penalise uncertain regions, the GP ensemble's variance of the step's velocity residuals."""

from __future__ import annotations

import numpy as np

from gpmppi.mppi.critics.base import Critic, critic_term


@critic_term
def variance_cost(weight: float, cost_w: np.ndarray, p: int, geo: tuple, at: tuple) -> float:
    return weight * (at.var_v + at.var_omega)


def noise_cost(weight: float, horizon: int, noise_v: float, noise_w: float) -> float:
    """The likelihood noise over the horizon: the predictive variance is the latent one plus the noise, and the
    kernels' exact GP gives the latent one (the grid table holds the predictive one: the noise is then 0 here)."""
    return horizon * weight * (noise_v + noise_w)


CRITIC = Critic("variance", 1.0, ("lane", "goal"), variance_cost,
                "sum of var_v + var_omega over the steps [cost / (m/s)^2]", noise_cost=noise_cost)
