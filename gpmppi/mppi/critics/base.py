"""What a critic is: its name, default weight and parameters, the task kinds it applies to, stage or terminal, and its
numba term; and what every term reads (the cost vector, the task's geometry, the step).

A term is `term(weight, cost_w, p, geo, at) -> float` (a stateful critic's: `term(weight, cost_w, p, geo, at, value)`),
compiled by `critic_term`:

* `weight` its weight; `cost_w` the cost vector the kernels hold (`registry.CriticLayout`), `p` the index in it of
  the critic's first parameter (in the order of `Critic.params`);
* `geo` the task, its `TaskBundle` fields by name (`geo.speed_target`, `geo.obstacles`, ...); `at` the step, a `Step`
  read by name: the state after the step, its command and GP variances, this step's tightened lane half-width and
  inflated obstacle radii, the stateful critics' values of this step, and (lane tasks) the lane distance and
  direction at the state;
* `value` (stateful critics, `Critic.state`): the critic's own value of this step (`StepState`).

What else a critic needs, it declares, and the drivers and the planner provide it without knowing its name: a value
carried from step to step (`Critic.state`, `StepState`: the lane-exit discount^k), the cost of the likelihood noise
that the kernels' variances leave out under the exact GP (`Critic.noise_cost`: the variance critic's).

A terminal term is evaluated once, on the state after the last step (its command and variances zero).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numba import njit

from gpmppi.kernel_flags import FASTMATH

__all__ = [
    "LANE_TASK_KINDS", "TASK_GOAL", "TASK_KINDS", "TASK_LANE", "W_GOAL_GEODESIC", "Critic", "Param", "Step",
    "StepState", "critic_term",
]

# task kinds of the rollout kernels, by the name the config uses
TASK_LANE = 0
TASK_GOAL = 1
TASK_KINDS = {"lane": TASK_LANE, "goal": TASK_GOAL}
# the kernels' task kinds whose critics read the lane at each step (`Step.lane_dist`, `lane_tx`, `lane_ty`: queried
# once per step for all of them, `registry.ByKind`)
LANE_TASK_KINDS = frozenset({"lane"})

# the cost vector's first slot: goal critics measure the distance around the obstacles (1.0) or the straight line
W_GOAL_GEODESIC = 0


class Step(NamedTuple):
    """One rollout step as every critic's term reads it (`costs.stage_cost` builds it once per step for all)."""

    x: float  # state after the step [m, m, rad, m/s, rad/s]
    y: float
    yaw: float
    v: float
    omega: float
    v_ref: float  # the step's command [m/s, rad/s]
    omega_ref: float
    var_v: float  # the step's GP residual variances [(m/s)^2, (rad/s)^2]
    var_omega: float
    tightened_hw: float  # this step's tightened lane half-width [m]
    radii: np.ndarray  # (K,) this step's inflated obstacle radii [m]
    state: tuple  # the stateful critics' values of this step (registration order; each gets its own as `value`)
    lane_dist: float  # lane tasks: distance from the lane's centre line [m] (else 0)
    lane_tx: float  # lane tasks: the lane's direction at the state (unit; else 0)
    lane_ty: float


def critic_term(func: Callable) -> Callable:
    """Compile a critic's term with the kernels' flags, inlined into its callers in numba's IR: a term loaded from
    the cache as machine code could not be inlined by LLVM, and the kernels' code (and last bits) would then depend
    on what the process compiled before (`tests/test_determinism.py`)."""
    return njit(cache=True, fastmath=FASTMATH, inline="always")(func)


@dataclass(frozen=True)
class Param:
    """A critic parameter: its default (a float, or a bool held as 1.0 / 0.0 in the cost vector), what it is, and
    for a float the open-or-closed range it must lie in."""

    default: float | bool
    description: str
    low: float = float("-inf")
    high: float = float("inf")
    low_open: bool = False

    def check(self, critic: str, name: str, value: object) -> float | bool:
        """`value` as the config holds it, or a ValueError saying what it must be."""
        where = f"critics.{critic}.{name}"
        if isinstance(self.default, bool):
            if not isinstance(value, bool):
                raise ValueError(f"{where} must be true or false, got {value!r}")
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{where} must be a number, got {value!r}")
        v = float(value)
        below = v <= self.low if self.low_open else v < self.low
        if not (v == v) or below or v > self.high:
            bound = "(" if self.low_open else "["
            raise ValueError(f"{where} must lie in {bound}{self.low}, {self.high}], got {value!r}")
        return v


@dataclass(frozen=True)
class StepState:
    """A value a critic carries from step to step of a rollout (the lane-exit critic's discount^k): `start(cost_w, p)`
    before the first step, `advance(value, cost_w, p)` after each (both compiled by `critic_term`; `cost_w` and `p` as
    the term's). The rollout drivers hold it (every stateful critic's, `registry.build_states`) and hand the critic
    its own as the term's last argument. It may depend on the step and the critic's parameters, not on the sample:
    the drivers hold one per step for all the samples they step together. A terminal term gets the value after the
    last step."""

    start: Callable
    advance: Callable


@dataclass(frozen=True)
class Critic:
    """One cost term: its name (the config's key), default weight, the task kinds it applies to ('lane', 'goal'),
    whether it is counted once at the horizon's end (`terminal`) or at every step, its parameters and its term; what
    it needs beyond the step: `state` (a value carried from step to step, `StepState`) and `noise_cost`
    (`noise_cost(weight, horizon, noise_v, noise_w)`: a critic of the step's variances, the cost over the horizon of
    the likelihood noise the kernels leave out of them when the GP gives latent variances; the planner adds it to
    every rollout's cost and to the critic's share)."""

    name: str
    weight: float
    tasks: tuple[str, ...]
    term: Callable
    description: str
    terminal: bool = False
    params: dict[str, Param] = field(default_factory=dict)
    state: StepState | None = None
    noise_cost: Callable[[float, int, float, float], float] | None = None
