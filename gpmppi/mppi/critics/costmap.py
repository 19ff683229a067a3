"""Costmap critic: obstacles from an occupancy grid (`gpmppi.costmap.Costmap`), with the chance constraint.

At each step the distance from the rollout point to the nearest lethal cell (the grid's distance transform, bilinear
between cell centres) is compared with this step's radius: the robot radius, half a cell's diagonal, and the
quantile radius of the propagated position covariance, Phi^-1(p_x) sqrt(lambda_max(Sigma_XY)) (the circles' quantile,
in the worst direction: a grid has obstacles on every side). The task bundle carries that radius per step as the
last column of `radii` (after the K circles'; `task_kinds.GoalKind.bounds`). Closer than it: `weight` (the collision
cost). Elsewhere: `weight * value_scale` times the cell's value as a fraction of the lethal threshold. Outside the
grid, and with no grid (`grid_frame[0]` = 0): nothing.
"""

from __future__ import annotations

import numpy as np

from gpmppi.kernel_flags import fmax, fmin
from gpmppi.mppi.critics.base import Critic, Param, critic_term

# the grid frame's slots (`gpmppi.costmap.Costmap.kernel_arrays`)
_HAS_GRID, _OX, _OY, _COS, _SIN, _INV_RES = 0, 1, 2, 3, 4, 5
_FAR = 1.5 * 1.4142135623730951 + 1e-6  # [cells]: a cell's diagonal and a half


@critic_term
def grid_cell(frame: np.ndarray, w: int, h: int, x: float, y: float) -> tuple[bool, float, float]:
    """(inside the grid, the grid's x and y [cells]) of world point (x, y)."""
    dx = x - frame[_OX]
    dy = y - frame[_OY]
    gx = (frame[_COS] * dx + frame[_SIN] * dy) * frame[_INV_RES]  # in cells, in the grid's frame
    gy = (frame[_COS] * dy - frame[_SIN] * dx) * frame[_INV_RES]
    return gx >= 0.0 and gy >= 0.0 and gx < w and gy < h, gx, gy


@critic_term
def interpolated_distance(grid: np.ndarray, gx: float, gy: float) -> float:
    """The distance [m] to the nearest lethal cell centre at grid point (gx, gy) [cells], bilinear between the four
    nearest cell centres."""
    h = grid.shape[0]
    w = grid.shape[1]
    fc = fmin(fmax(gx - 0.5, 0.0), w - 1.0)  # (float min / max: the CUDA target compiles these)
    fr = fmin(fmax(gy - 0.5, 0.0), h - 1.0)
    c = int(fc)
    r = int(fr)
    c1 = c + 1 if c + 1 < w else c
    r1 = r + 1 if r + 1 < h else r
    tx = fc - c
    ty = fr - r
    return (1.0 - ty) * ((1.0 - tx) * grid[r, c, 1] + tx * grid[r, c1, 1]) + ty * (
        (1.0 - tx) * grid[r1, c, 1] + tx * grid[r1, c1, 1])


@critic_term
def grid_lookup(grid: np.ndarray, frame: np.ndarray, x: float, y: float) -> tuple[bool, float, float]:
    """(inside the grid, the interpolated distance [m] to the nearest lethal cell centre, the value fraction of the cell
    the point lies in) at world point (x, y)."""
    inside, gx, gy = grid_cell(frame, grid.shape[1], grid.shape[0], x, y)
    if not inside:
        return False, 0.0, 0.0
    return True, interpolated_distance(grid, gx, gy), grid[int(gy), int(gx), 0]


@critic_term
def costmap_cost(weight: float, cost_w: np.ndarray, p: int, geo: tuple, at: tuple) -> float:
    frame = geo.grid_frame
    if frame[_HAS_GRID] == 0.0 or weight == 0.0:
        return 0.0
    grid = geo.grid
    inside, gx, gy = grid_cell(frame, grid.shape[1], grid.shape[0], at.x, at.y)
    if not inside:
        return 0.0
    r = int(gy)
    c = int(gx)
    radius = at.radii[geo.obstacles.shape[0]]  # this step's radius: the column after the circles'
    # the interpolation only where it can decide: the four centres it reads lie within a cell's diagonal of the point
    # and the point within half of one of its own cell's centre, so a cell this far off leaves it above the radius
    if grid[r, c, 1] <= radius + _FAR / frame[_INV_RES] and interpolated_distance(grid, gx, gy) < radius:
        return weight
    return weight * cost_w[p] * grid[r, c, 0]  # p: `value_scale`


CRITIC = Critic("costmap", 1000.0, ("goal",), costmap_cost,
                "within the step's radius of a lethal grid cell: weight; elsewhere weight * value_scale * the "
                "cell's value / lethal [cost]",
                params={"value_scale": Param(0.01, "the share of the weight a cell at the lethal value would cost "
                                                   "per step, for the cells below it (dimensionless)", low=0.0,
                                             high=1.0)})
