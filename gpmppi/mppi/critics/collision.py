"""Collision critic: the indicator of being inside any inflated obstacle circle at a step."""

from __future__ import annotations

import numpy as np

from gpmppi.mppi.critics.base import Critic, critic_term


@critic_term
def collision_cost(weight: float, cost_w: np.ndarray, p: int, geo: tuple, at: tuple) -> float:
    obstacles = geo.obstacles
    radii = at.radii
    x = at.x
    y = at.y
    for j in range(obstacles.shape[0]):
        dx = x - obstacles[j, 0]
        dy = y - obstacles[j, 1]
        r = radii[j]
        if dx * dx + dy * dy < r * r:  # squared distance against squared radius
            return weight
    return 0.0


CRITIC = Critic("collision", 1000.0, ("goal",), collision_cost, "inside an inflated obstacle at a step [cost]")
