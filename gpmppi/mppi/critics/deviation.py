"""Deviation critic: the distance to the lane's centre line, normalised by the nominal half-width, squared."""

from __future__ import annotations

import numpy as np

from gpmppi.mppi.critics.base import Critic, critic_term


@critic_term
def deviation_cost(weight: float, cost_w: np.ndarray, p: int, geo: tuple, at: tuple) -> float:
    e = at.lane_dist / geo.half_width
    return weight * e * e


CRITIC = Critic("deviation", 300.0, ("lane",), deviation_cost, "(d / r)^2 per step [cost]")
