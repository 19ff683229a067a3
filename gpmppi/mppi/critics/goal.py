"""Goal critic: the distance to the goal at every step, around the obstacles (the goal-distance field) or in a
straight line (the planner's `goal_distance`, the cost vector's `W_GOAL_GEODESIC`)."""

from __future__ import annotations

import math

import numpy as np

from gpmppi.mppi.critics.base import W_GOAL_GEODESIC, Critic, critic_term
from gpmppi.mppi.goal_field import goal_distance


@critic_term
def straight_goal_cost(x: float, y: float, goal: np.ndarray, weight: float) -> float:
    """`weight` times the straight-line distance to the goal."""
    dx = x - goal[0]
    dy = y - goal[1]
    return weight * math.sqrt(dx * dx + dy * dy)


@critic_term
def goal_term(
    cost_w: np.ndarray, field: np.ndarray, origin: np.ndarray, inv_cell: float, goal: np.ndarray, x: float, y: float,
    weight: float,
) -> float:
    """`weight` times the distance to the goal from (x, y), around the obstacles or straight (`W_GOAL_GEODESIC`)."""
    if cost_w[W_GOAL_GEODESIC] > 0.0:
        return weight * goal_distance(field, origin, inv_cell, x, y)
    return straight_goal_cost(x, y, goal, weight)


@critic_term
def goal_cost(weight: float, cost_w: np.ndarray, p: int, geo: tuple, at: tuple) -> float:
    return goal_term(cost_w, geo.field, geo.origin, geo.inv_cell, geo.goal, at.x, at.y, weight)


CRITIC = Critic("goal", 1.0, ("goal",), goal_cost, "distance to the goal per step [cost / m]")
