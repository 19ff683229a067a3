"""Lane-exit critic: the indicator of being outside the tightened lane, discounted along the horizon (discount^k).

The rollout drivers hold discount^k (`AT_DISCOUNT_K`), multiplied step by step from this critic's `discount`."""

from __future__ import annotations

import numpy as np

from gpmppi.mppi.critics.base import Critic, Param, critic_term


@critic_term
def lane_exit_cost(weight: float, cost_w: np.ndarray, p: int, geo: tuple, at: tuple) -> float:
    return weight * at.discount_k if at.lane_dist > at.tightened_hw else 0.0


CRITIC = Critic("lane_exit", 1000.0, ("lane",), lane_exit_cost,
                "outside the tightened lane at step k costs weight * discount^k [cost]",
                params={"discount": Param(0.9, "discount per step (dimensionless)", low=0.0, high=1.0,
                                          low_open=True)})
