"""Tracking and avoidance costs, and chance-constraint tightening.

Costs are critic-style (as Nav2 MPPI): each term is a small numba function with its own weight,
evaluated on the state after every rollout step k = 0..N-1 (the terminal term once on x_N).

* tracking (lane):   variance + deviation (d / r)^2 + slip + discount^k [d > r_bar_k] + (v_lane - v_target)^2
  where v_lane = v cos(yaw - lane direction) is the speed along the lane (the polyline's order is
  the driving direction); with `speed_along_lane` off it is the speed v itself, as the paper
  writes it, which rewards speed in any direction: at a square track's corners the robot then
  kept its speed through loops instead of slowing into the turn.
* avoidance (goal):  variance + [inside an inflated circle] + D(p) per step + terminal D(p_N), where D is
  the length of the shortest path to the goal around the circles (`gpmppi.mppi.goal_field`), or the
  straight-line distance |p - goal| as in the paper when `goal_distance="euclidean"` (that one has
  local minima in pockets between circles)

The variance term (GP ensemble variance of the step's velocity residual) is counted at every step.

Tightening (chance constraints at probability p_x, from the propagated covariance Sigma_XY):

* lane half-width  r_bar = r - sqrt(chi2_2(p_x) * lambda_max(Sigma_XY)), clamped to >= min_fraction * r
* obstacle radius  r_j + Phi^-1(p_x) * sqrt(n^T Sigma_XY n) with n the unit vector from the obstacle
  centre to the nominal position, the inflation capped at `max_inflation`.
* grid radius      r + Phi^-1(p_x) * sqrt(lambda_max(Sigma_XY)), capped alike (`inflate_grid`): the same quantile in
  the worst direction, since a grid's lethal cells may lie on every side of the nominal position.

Quantiles come from scipy once per configuration (`ChanceQuantiles`), never per step: the inverse
functions scipy.stats's `chi2.ppf` and `norm.ppf` evaluate, called directly (importing scipy.stats
took ~0.35 s of every planner start; tests check them against scipy.stats).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.special import chdtri, ndtri

from gpmppi.kernel_flags import FASTMATH
from gpmppi.mppi.bundles import CRITICS
from gpmppi.mppi.critics.base import Step
from gpmppi.mppi.critics.registry import build_by_kind, build_states, build_sums
from gpmppi.mppi.lane import lane_query

__all__ = [
    "BY_KIND", "CRITICS", "STATES", "SUMS", "ChanceQuantiles", "advance_state", "fill_weight_vector", "inflate_grid",
    "inflate_obstacles",
    "lane_stage_cost_at", "plain_stage_cost", "stage_cost", "stage_reads_lane", "stage_critics", "start_state",
    "terminal_cost", "terminal_critics", "tighten_lane", "weight_vector", "xy_lambda_max",
]

# the registered critics' terms, summed and split, per task kind (`gpmppi.mppi.critics.registry`; the CUDA backend
# makes each of these functions' device twin from the same terms), and the sums of a step's own kind (`BY_KIND`)
SUMS = build_sums()
BY_KIND = build_by_kind(SUMS)
_stage = BY_KIND.stage
_stage_split = BY_KIND.stage_split
_terminal = BY_KIND.terminal
_terminal_split = BY_KIND.terminal_split
_lane_stage = BY_KIND.lane_stage  # whether a kind's stage critics read the lane (the step then queries it)
stage_reads_lane = _lane_stage  # the same, for the CPU kernel's lane phase (`cpu_backend._add_costs`)
_lane_terminal = BY_KIND.lane_terminal  # whether a kind's terminal critics read the lane at the horizon's end
_stage_lane = BY_KIND.stage_lane  # `_stage` over the kinds whose stage critics read the lane, and over the others
_stage_plain = BY_KIND.stage_plain
# the stateful critics' values, carried by the drivers from step to step (`registry.build_states`)
STATES = build_states()
start_state = STATES.start  # start_state(cost_w): the values at a rollout's first step
advance_state = STATES.advance  # advance_state(state, cost_w): the next step's


@njit(cache=True, inline="always")
def fill_weight_vector(cost: tuple, w: np.ndarray) -> None:
    """Write the cost bundle's tuple (`CostBundle.args()`) into `w` (`N_COST_TERMS`,): the vector the kernels
    read (`weight_vector`)."""
    for i in range(len(cost)):
        w[i] = cost[i]


@njit(cache=True, inline="always")
def weight_vector(cost: tuple) -> np.ndarray:
    """The cost bundle's tuple as the float64 vector the kernels read, built once per call, before any loop.

    Why a vector and not the tuple's scalars: under fastmath reassociation LLVM orders the operands of the
    cost sums by where their values come from, and weights read from memory inside the loops (as before
    the bundles) keep the kernels' rounding, so seeded plans are unchanged."""
    w = np.empty(len(cost))
    fill_weight_vector(cost, w)
    return w


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _step(
    query_lane: bool, task: tuple, tightened_hw: float, radii: np.ndarray, state: tuple, s: tuple, u: tuple,
    var: tuple,
) -> Step:
    """What the critics' terms read of a step (`critics.base.Step`); with `query_lane` the lane query at the state,
    once for all the lane critics (else zeros)."""
    px, py, yaw, v, w = s
    d, tx, ty = 0.0, 0.0, 0.0
    if query_lane:
        d, tx, ty = lane_query(task.seg, task.cell_start, task.candidates, task.field, task.origin, task.inv_cell, px,
                               py, tightened_hw)
    return Step(px, py, yaw, v, w, u[0], u[1], var[0], var[1], tightened_hw, radii, state, d, tx, ty)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _step_off_lane(
    query_lane: bool, task: tuple, tightened_hw: float, radii: np.ndarray, state: tuple, s: tuple, u: tuple,
    var: tuple,
) -> Step:
    """`_step` where no kind's critics read the lane there (`query_lane` is then False for every kind): the same step
    without a lane query compiled in (it would be dead code, but numba compiles it before LLVM drops it)."""
    px, py, yaw, v, w = s
    return Step(px, py, yaw, v, w, u[0], u[1], var[0], var[1], tightened_hw, radii, state, 0.0, 0.0, 0.0)


# the terminal step: no registered kind's terminal critics read the lane (the shipped critics), so no lane query
_terminal_step = _step if BY_KIND.any_lane_terminal else _step_off_lane


@njit(cache=True, fastmath=FASTMATH, inline="always")
def stage_cost(
    cost_w: np.ndarray, task: tuple, tightened_hw: float, radii: np.ndarray, state: tuple, s: tuple, u: tuple,
    var: tuple,
) -> float:
    """Cost of one rollout step: the sum of the task kind's stage critics, in `CRITICS` order.

    `cost_w` the cost bundle as the kernels hold it (`weight_vector`); `task` the task bundle's tuple (`TaskArgs`;
    the critics read its geometry by name); `tightened_hw` this step's tightened half-width (the lane distance is
    exact near it), `radii` (K,) this step's inflated radii; `state` the stateful critics' values of this step
    (`start_state`, `advance_state`); `s` the state after the step (x, y, yaw, v, omega), `u` its command, `var` its
    GP variances. `task.kind` picks the critics (`BY_KIND`): one of the kernels' task kinds, as `TaskBundle.args`
    refuses any other.
    """
    at = _step(_lane_stage(task.kind), task, tightened_hw, radii, state, s, u, var)
    return _stage(task.kind, 0.0, cost_w, task, at)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def lane_stage_cost_at(
    cost_w: np.ndarray, task: tuple, tightened_hw: float, radii: np.ndarray, state: tuple, s: tuple, u: tuple,
    var: tuple, lane: tuple,
) -> float:
    """`stage_cost` of a task whose stage critics read the lane (`stage_reads_lane`), given its lane query at the
    state, `lane` = (d, tx, ty) (`lane.lane_query`): the CPU kernel queries a group's lane in loops of their own
    (`cpu_backend._add_costs`)."""
    px, py, yaw, v, w = s
    at = Step(px, py, yaw, v, w, u[0], u[1], var[0], var[1], tightened_hw, radii, state, lane[0], lane[1], lane[2])
    return _stage_lane(task.kind, 0.0, cost_w, task, at)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def plain_stage_cost(
    cost_w: np.ndarray, task: tuple, tightened_hw: float, radii: np.ndarray, state: tuple, s: tuple, u: tuple,
    var: tuple,
) -> float:
    """`stage_cost` of a task whose stage critics do not read the lane (not `stage_reads_lane`): no lane query
    compiled in, and only those kinds' critics (the CPU kernel's `_add_costs` branches on `stage_reads_lane` first,
    so each kind's critics are compiled into it once)."""
    at = _step_off_lane(False, task, tightened_hw, radii, state, s, u, var)
    return _stage_plain(task.kind, 0.0, cost_w, task, at)


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def stage_critics(
    cost_w: np.ndarray, task: tuple, tightened_hw: float, radii: np.ndarray, state: tuple, s: tuple, u: tuple,
    var: tuple, out: np.ndarray,
) -> None:
    """Add each stage critic's cost of one step to `out` (`CRITICS` order; arguments as `stage_cost`): the kernels
    need only the sum, the plan reports each."""
    at = _step(_lane_stage(task.kind), task, tightened_hw, radii, state, s, u, var)
    _stage_split(task.kind, cost_w, task, at, out)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def terminal_cost(
    cost_w: np.ndarray, task: tuple, tightened_hw: float, radii: np.ndarray, state: tuple, s: tuple,
) -> float:
    """The sum of the task kind's terminal critics at the state after the last step (`s`; bounds of that step; `state`
    the stateful critics' values after it)."""
    at = _terminal_step(_lane_terminal(task.kind), task, tightened_hw, radii, state, s, (0.0, 0.0), (0.0, 0.0))
    return _terminal(task.kind, 0.0, cost_w, task, at)


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def terminal_critics(
    cost_w: np.ndarray, task: tuple, tightened_hw: float, radii: np.ndarray, state: tuple, s: tuple, out: np.ndarray,
) -> None:
    """Add each terminal critic's cost to `out` (`CRITICS` order; arguments as `terminal_cost`)."""
    at = _terminal_step(_lane_terminal(task.kind), task, tightened_hw, radii, state, s, (0.0, 0.0), (0.0, 0.0))
    _terminal_split(task.kind, cost_w, task, at, out)


@dataclass(frozen=True)
class ChanceQuantiles:
    """Quantiles for chance constraints at probability `p_x` (computed once per configuration)."""

    p_x: float
    chi2_2: float  # chi-square quantile with 2 degrees of freedom
    normal: float  # standard normal quantile Phi^-1(p_x)

    @classmethod
    def for_probability(cls, p_x: float) -> ChanceQuantiles:
        if not (0.0 < p_x < 1.0):
            raise ValueError(f"p_x must be a probability in (0, 1), got {p_x}")
        return cls(float(p_x), float(chdtri(2, 1.0 - p_x)), float(ndtri(p_x)))


@njit(cache=True)
def xy_lambda_max(cov: np.ndarray) -> float:
    """Largest eigenvalue of the XY block of a 5x5 covariance (closed form for 2x2 symmetric)."""
    a = cov[0, 0]
    b = 0.5 * (cov[0, 1] + cov[1, 0])
    c = cov[1, 1]
    half_tr = 0.5 * (a + c)
    disc = np.sqrt(max(0.25 * (a - c) * (a - c) + b * b, 0.0))
    return max(half_tr + disc, 0.0)


@njit(cache=True)
def tighten_lane(covs: np.ndarray, half_width: float, chi2_q: float, min_fraction: float) -> tuple[np.ndarray, int]:
    """(N+1,) tightened half-widths from (N+1, 5, 5) covariances, and how many steps were clamped."""
    n = covs.shape[0]
    out = np.empty(n)
    floor = min_fraction * half_width
    clamped = 0
    for k in range(n):
        r = half_width - np.sqrt(chi2_q * xy_lambda_max(covs[k]))
        if r < floor:
            r = floor
            clamped += 1
        out[k] = r
    return out, clamped


@njit(cache=True)
def inflate_obstacles(
    states: np.ndarray, covs: np.ndarray, obstacles: np.ndarray, normal_q: float, extra: float, max_inflation: float
) -> tuple[np.ndarray, int]:
    """(N+1, K) effective radii r_j + extra + min(Phi^-1(p) sqrt(n^T S n), cap), and the number capped.

    `extra` is the robot radius. When the nominal position sits on the centre (no direction) the
    worst direction (largest eigenvalue) is used.
    """
    n = states.shape[0]
    k_n = obstacles.shape[0]
    out = np.empty((n, k_n))
    capped = 0
    for k in range(n):
        sxx = covs[k, 0, 0]
        sxy = 0.5 * (covs[k, 0, 1] + covs[k, 1, 0])
        syy = covs[k, 1, 1]
        for j in range(k_n):
            dx = states[k, 0] - obstacles[j, 0]
            dy = states[k, 1] - obstacles[j, 1]
            d = np.sqrt(dx * dx + dy * dy)
            if d > 1e-9:
                nx = dx / d
                ny = dy / d
                s2 = nx * nx * sxx + 2.0 * nx * ny * sxy + ny * ny * syy
            else:
                s2 = xy_lambda_max(covs[k])
            infl = normal_q * np.sqrt(max(s2, 0.0))
            if infl > max_inflation:
                infl = max_inflation
                capped += 1
            out[k, j] = obstacles[j, 2] + extra + max(infl, 0.0)
    return out, capped


def inflate_grid(covs: np.ndarray, normal_q: float, radius: float, max_inflation: float) -> tuple[np.ndarray, int]:
    """(N+1,) radii around a grid's lethal cells, radius + min(Phi^-1(p) sqrt(lambda_max(Sigma_XY)), cap), from (N+1,
    5, 5) covariances, and the number capped."""
    a = covs[:, 0, 0]
    b = 0.5 * (covs[:, 0, 1] + covs[:, 1, 0])
    c = covs[:, 1, 1]
    lam = np.maximum(0.5 * (a + c) + np.sqrt(np.maximum(0.25 * (a - c) ** 2 + b * b, 0.0)), 0.0)
    infl = normal_q * np.sqrt(lam)
    capped = int(np.count_nonzero(infl > max_inflation))
    return radius + np.clip(infl, 0.0, max_inflation), capped
