"""Lane-exit critic: the indicator of being outside the tightened lane, discounted along the horizon (discount^k).

discount^k is the critic's state (`base.StepState`): 1 at the first step, times `discount` after each; the rollout
drivers carry it and hand it to the term."""

from __future__ import annotations

import numpy as np

from gpmppi.mppi.critics.base import Critic, Param, StepState, critic_term


@critic_term
def lane_exit_cost(
    weight: float, cost_w: np.ndarray, p: int, geo: tuple, at: tuple, discount_k: float,
) -> float:
    return weight * discount_k if at.lane_dist > at.tightened_hw else 0.0


@critic_term
def first_discount(cost_w: np.ndarray, p: int) -> float:
    return 1.0


@critic_term
def next_discount(discount_k: float, cost_w: np.ndarray, p: int) -> float:
    return discount_k * cost_w[p]  # p: `discount`


CRITIC = Critic("lane_exit", 1000.0, ("lane",), lane_exit_cost,
                "outside the tightened lane at step k costs weight * discount^k [cost]",
                params={"discount": Param(0.9, "discount per step (dimensionless)", low=0.0, high=1.0,
                                          low_open=True)},
                state=StepState(first_discount, next_discount))
