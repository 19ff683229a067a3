"""Terminal critic: the distance to the goal at the horizon's end (measured as the goal critic measures it)."""

from __future__ import annotations

import numpy as np

from gpmppi.mppi.critics.base import Critic, critic_term
from gpmppi.mppi.critics.goal import goal_term


@critic_term
def terminal_cost(weight: float, cost_w: np.ndarray, p: int, geo: tuple, at: tuple) -> float:
    return goal_term(cost_w, geo.field, geo.origin, geo.inv_cell, geo.goal, at.x, at.y, weight)


CRITIC = Critic("terminal", 10.0, ("goal",), terminal_cost, "distance to the goal at the horizon's end [cost / m]",
                terminal=True)
