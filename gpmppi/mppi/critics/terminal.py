"""Terminal critic: the distance to the goal at the horizon's end (measured as the goal critic measures it)."""

from __future__ import annotations

import numpy as np

from gpmppi.mppi.critics.base import AT_X, AT_Y, G_FIELD, G_GOAL, G_INV_CELL, G_ORIGIN, Critic, critic_term
from gpmppi.mppi.critics.goal import goal_term


@critic_term
def terminal_cost(weight: float, cost_w: np.ndarray, p: int, geo: tuple, at: tuple) -> float:
    return goal_term(cost_w, geo[G_FIELD], geo[G_ORIGIN], geo[G_INV_CELL], geo[G_GOAL], at[AT_X], at[AT_Y], weight)


CRITIC = Critic("terminal", 10.0, ("goal",), terminal_cost, "distance to the goal at the horizon's end [cost / m]",
                terminal=True)
