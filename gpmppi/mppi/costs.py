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

Quantiles come from scipy once per configuration (`ChanceQuantiles`), never per step: the inverse
functions scipy.stats's `chi2.ppf` and `norm.ppf` evaluate, called directly (importing scipy.stats
took ~0.35 s of every planner start; tests check them against scipy.stats).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.special import chdtri, ndtri

from gpmppi.kernel_flags import FASTMATH
from gpmppi.mppi.bundles import (
    CRITICS,
    K_COLLISION,
    K_DEVIATION,
    K_EXIT_DISCOUNT,
    K_GOAL,
    K_GOAL_GEODESIC,
    K_LANE_EXIT,
    K_SLIP,
    K_SPEED,
    K_SPEED_ALONG_LANE,
    K_TERMINAL,
    K_VARIANCE,
    N_COST_TERMS,
    TASK_GOAL,
    TASK_LANE,
)
from gpmppi.mppi.goal_field import goal_distance
from gpmppi.mppi.lane import lane_query

__all__ = [
    "CRITICS", "TASK_GOAL", "TASK_LANE", "ChanceQuantiles", "collision_cost", "deviation_cost", "goal_cost",
    "goal_term", "inflate_obstacles", "lane_exit_cost", "slip_cost", "speed_cost", "stage_cost", "stage_critics",
    "tighten_lane", "variance_cost", "weight_vector", "fill_weight_vector", "xy_lambda_max",
]


@njit(cache=True, fastmath=FASTMATH, inline="always")
def variance_cost(var_v: float, var_w: float, weight: float) -> float:
    """Penalise uncertain regions: the ensemble variance of the step's velocity residuals."""
    return weight * (var_v + var_w)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def deviation_cost(dist: float, half_width: float, weight: float) -> float:
    """Lane deviation normalised by the nominal half-width."""
    e = dist / half_width
    return weight * e * e


@njit(cache=True, fastmath=FASTMATH, inline="always")
def slip_cost(v: float, w: float, v_ref: float, w_ref: float, weight: float) -> float:
    """Gap between the commanded and the resulting velocities (slip / lag of the base)."""
    dv = v_ref - v
    dw = w_ref - w
    return weight * (dv * dv + dw * dw)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def lane_exit_cost(dist: float, tightened_half_width: float, discount_k: float, weight: float) -> float:
    """Indicator of leaving the tightened lane, discounted along the horizon (discount^k)."""
    return weight * discount_k if dist > tightened_half_width else 0.0


@njit(cache=True, fastmath=FASTMATH, inline="always")
def speed_cost(v: float, target: float, weight: float) -> float:
    """Shortfall or excess of the speed (along the lane, see the module notes) against the target."""
    e = v - target
    return weight * e * e


@njit(cache=True, fastmath=FASTMATH, inline="always")
def collision_cost(x: float, y: float, obstacles: np.ndarray, radii: np.ndarray, weight: float) -> float:
    """Indicator of being inside any circle; `radii` (K,) are the inflated radii at this step."""
    for j in range(obstacles.shape[0]):
        dx = x - obstacles[j, 0]
        dy = y - obstacles[j, 1]
        r = radii[j]
        if dx * dx + dy * dy < r * r:  # squared distance against squared radius
            return weight
    return 0.0


@njit(cache=True, fastmath=FASTMATH, inline="always")
def goal_cost(x: float, y: float, goal: np.ndarray, weight: float) -> float:
    """Euclidean distance to the goal (stage term; the terminal term uses the same with its weight)."""
    dx = x - goal[0]
    dy = y - goal[1]
    return weight * math.sqrt(dx * dx + dy * dy)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def goal_term(
    cost_w: np.ndarray, field: np.ndarray, origin: np.ndarray, inv_cell: float, goal: np.ndarray, x: float, y: float,
    weight: float,
) -> float:
    """Distance-to-goal term: around the obstacles (`field`) or in a straight line (by the switch in `cost_w`,
    `weight_vector`), times `weight`."""
    if cost_w[K_GOAL_GEODESIC] > 0.0:
        return weight * goal_distance(field, origin, inv_cell, x, y)
    return goal_cost(x, y, goal, weight)


@njit(cache=True, inline="always")
def fill_weight_vector(cost: tuple, w: np.ndarray) -> None:
    """Write the cost bundle's tuple (`CostBundle.args()`) into `w` (`N_COST_TERMS`,) by the same `K_*` (switches
    1.0 on, 0.0 off): the vector the kernels read (`weight_vector`)."""
    w[K_VARIANCE] = cost[K_VARIANCE]
    w[K_DEVIATION] = cost[K_DEVIATION]
    w[K_SLIP] = cost[K_SLIP]
    w[K_LANE_EXIT] = cost[K_LANE_EXIT]
    w[K_SPEED] = cost[K_SPEED]
    w[K_COLLISION] = cost[K_COLLISION]
    w[K_GOAL] = cost[K_GOAL]
    w[K_TERMINAL] = cost[K_TERMINAL]
    w[K_EXIT_DISCOUNT] = cost[K_EXIT_DISCOUNT]
    w[K_SPEED_ALONG_LANE] = 1.0 if cost[K_SPEED_ALONG_LANE] else 0.0
    w[K_GOAL_GEODESIC] = 1.0 if cost[K_GOAL_GEODESIC] else 0.0


@njit(cache=True, inline="always")
def weight_vector(cost: tuple) -> np.ndarray:
    """The cost bundle's tuple as the float64 vector the kernels read, built once per call, before any loop.

    Why a vector and not the tuple's scalars: under fastmath reassociation LLVM orders the operands of the
    cost sums by where their values come from, and weights read from memory inside the loops (as before
    the bundles) keep the kernels' rounding, so seeded plans are unchanged."""
    w = np.empty(N_COST_TERMS)
    fill_weight_vector(cost, w)
    return w


@njit(cache=True, fastmath=FASTMATH, inline="always")
def stage_cost(
    kind: int, cost_w: np.ndarray, geo: tuple, tightened_hw: float, radii: np.ndarray, discount_k: float, s: tuple,
    u: tuple, var: tuple,
) -> float:
    """Cost of one rollout step, the sum of the stage critics (`stage_critics`, in `CRITICS` order).

    `cost_w` the cost bundle as the kernels hold it (`weight_vector`); `geo` the task's geometry (seg,
    cell_start, candidates, field, origin, inv_cell, half_width, speed_target, goal, obstacles: `TaskBundle`
    fields); `tightened_hw` this
    step's tightened half-width (the lane distance is exact near it), `radii` (K,) this step's inflated
    radii; `s` the state after the step (x, y, yaw, v, omega), `u` its command, `var` its GP variances.
    """
    seg, cell_start, candidates, field, origin, inv_cell, half_width, speed_target, goal, obstacles = geo
    px, py, yaw, v, w = s
    c = variance_cost(var[0], var[1], cost_w[K_VARIANCE])
    if kind == TASK_LANE:
        d, tx, ty = lane_query(seg, cell_start, candidates, field, origin, inv_cell, px, py, tightened_hw)
        c += deviation_cost(d, half_width, cost_w[K_DEVIATION])
        c += slip_cost(v, w, u[0], u[1], cost_w[K_SLIP])
        c += lane_exit_cost(d, tightened_hw, discount_k, cost_w[K_LANE_EXIT])
        v_lane = v * (math.cos(yaw) * tx + math.sin(yaw) * ty) if cost_w[K_SPEED_ALONG_LANE] > 0.0 else v
        c += speed_cost(v_lane, speed_target, cost_w[K_SPEED])
    else:
        c += collision_cost(px, py, obstacles, radii, cost_w[K_COLLISION])
        c += goal_term(cost_w, field, origin, inv_cell, goal, px, py, cost_w[K_GOAL])
    return c


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def stage_critics(
    kind: int, cost_w: np.ndarray, geo: tuple, tightened_hw: float, radii: np.ndarray, discount_k: float, s: tuple,
    u: tuple, var: tuple, out: np.ndarray,
) -> None:
    """Add each stage critic's cost of one step to `out` (`CRITICS` order; arguments as `stage_cost`).

    The same terms as `stage_cost`, kept apart: the rollout kernels need only their sum, the plan reports each.
    """
    seg, cell_start, candidates, field, origin, inv_cell, half_width, speed_target, goal, obstacles = geo
    px, py, yaw, v, w = s
    out[K_VARIANCE] += variance_cost(var[0], var[1], cost_w[K_VARIANCE])
    if kind == TASK_LANE:
        d, tx, ty = lane_query(seg, cell_start, candidates, field, origin, inv_cell, px, py, tightened_hw)
        out[K_DEVIATION] += deviation_cost(d, half_width, cost_w[K_DEVIATION])
        out[K_SLIP] += slip_cost(v, w, u[0], u[1], cost_w[K_SLIP])
        out[K_LANE_EXIT] += lane_exit_cost(d, tightened_hw, discount_k, cost_w[K_LANE_EXIT])
        v_lane = v * (math.cos(yaw) * tx + math.sin(yaw) * ty) if cost_w[K_SPEED_ALONG_LANE] > 0.0 else v
        out[K_SPEED] += speed_cost(v_lane, speed_target, cost_w[K_SPEED])
    else:
        out[K_COLLISION] += collision_cost(px, py, obstacles, radii, cost_w[K_COLLISION])
        out[K_GOAL] += goal_term(cost_w, field, origin, inv_cell, goal, px, py, cost_w[K_GOAL])


assert len(CRITICS) == 8 and CRITICS[K_GOAL] == "goal"  # the K_* of the critics index CRITICS too


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
