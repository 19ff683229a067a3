"""Slip critic: the gap between the commanded and the resulting velocities (slip, or lag of the base)."""

from __future__ import annotations

import numpy as np

from gpmppi.mppi.critics.base import Critic, critic_term


@critic_term
def slip_cost(weight: float, cost_w: np.ndarray, p: int, geo: tuple, at: tuple) -> float:
    dv = at.v_ref - at.v
    dw = at.omega_ref - at.omega
    return weight * (dv * dv + dw * dw)


CRITIC = Critic("slip", 0.1, ("lane",), slip_cost, "(v_ref - v)^2 + (omega_ref - omega)^2 per step [cost / (m/s)^2]")
