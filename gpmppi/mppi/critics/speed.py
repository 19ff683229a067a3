"""Speed critic: shortfall or excess of the speed against the lane's speed target, squared.

With `along_lane` (default) the speed is the speed along the lane, v cos(yaw - lane direction) (the centre line's
point order is the driving direction); off, the speed itself, as the paper writes it, which rewards speed in any
direction: at a square track's corners the robot then kept its speed through loops instead of slowing into the
turn."""

from __future__ import annotations

import numpy as np

from gpmppi.mppi.critics.base import Critic, Param, critic_term
from gpmppi.trig import cos_sin


@critic_term
def speed_cost(weight: float, cost_w: np.ndarray, p: int, geo: tuple, at: tuple) -> float:
    v = at.v
    yaw = at.yaw
    if cost_w[p] > 0.0:
        c, s = cos_sin(yaw)
        v_lane = v * (c * at.lane_tx + s * at.lane_ty)
    else:
        v_lane = v
    e = v_lane - geo.speed_target
    return weight * e * e


CRITIC = Critic("speed", 2.0, ("lane",), speed_cost, "(v_lane - speed_target)^2 per step [cost / (m/s)^2]",
                params={"along_lane": Param(True, "on the speed along the lane (else the speed magnitude)")})
