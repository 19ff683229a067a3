"""Distance to the goal around the obstacles (geodesic), for the avoidance cost.

The straight-line distance to the goal has local minima wherever circles form a pocket that opens
towards the goal (two overlapping circles, a wall of them): every rollout that makes progress
collides, and the robot is drawn in. The length of the shortest collision-free path has no such
minima. `build_goal_field` computes it once per scene on a grid:

* cells that see the goal (the segment to it misses every circle) get the exact Euclidean distance;
* the rest get a shortest path through the free cells (Dijkstra, scipy) on a 16-neighbour stencil
  (error <= 2.7% of the part of the path that runs out of sight of the goal), started from the
  visible cells with their exact distances (a virtual source), so the field is exact wherever the
  goal is in sight and close to exact in an obstacle's shadow;
* cells inside a circle take the value of their nearest free cell plus the distance to it (the
  collision term prices them; this only keeps the field finite and continuous there);
* cells no path reaches (enclosed) take the largest reached value plus their Euclidean distance.

With an occupancy grid (`gpmppi.costmap.Costmap`) its lethal cells, grown by the clearance and by enough to close
them at the field's cell (half a field cell's diagonal), are blocked too; the path then starts from the goal's own
cell and its neighbours (no line-of-sight test through the grid), so the field is the 16-neighbour path length
everywhere (within 2.7%).

Queries interpolate bilinearly; outside the grid they add the distance to the grid's edge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from gpmppi.costmap import Costmap, lethal_radius
from gpmppi.kernel_flags import FASTMATH
from gpmppi.mppi.lane import grid_cell_at
from gpmppi.mppi.recent import Recent

# 16-neighbour stencil (one octant of it mirrored): unit steps, diagonals and knight moves
_STENCIL = np.array(
    [(1, 0), (0, 1), (-1, 0), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1),
     (2, 1), (1, 2), (-1, 2), (-2, 1), (-2, -1), (-1, -2), (1, -2), (2, -1)]
)


@dataclass(frozen=True)
class GoalField:
    """(H, W, 3) grid; channel 0 is the geodesic distance to the goal at the cell centres [m]."""

    field: np.ndarray
    origin: np.ndarray  # (2,) world position of cell (0, 0)'s corner [m]
    inv_cell: float  # 1 / cell size [1/m]
    reachable: bool  # False when no free path reaches the goal from anywhere outside the circles


def _segment_clear(px: np.ndarray, py: np.ndarray, goal: np.ndarray, circles: np.ndarray) -> np.ndarray:
    """For each point, whether the segment to the goal misses every circle (x, y, r)."""
    clear = np.ones(px.shape, dtype=bool)
    dx = goal[0] - px
    dy = goal[1] - py
    len2 = np.maximum(dx * dx + dy * dy, 1e-18)
    for cx, cy, r in circles:
        t = np.clip(((cx - px) * dx + (cy - py) * dy) / len2, 0.0, 1.0)
        ex = px + t * dx - cx
        ey = py + t * dy - cy
        clear &= ex * ex + ey * ey >= r * r
    return clear


def build_goal_field(
    goal: np.ndarray, circles: np.ndarray, extent_points: np.ndarray, margin: float = 3.0, cell: float = 0.1,
    max_cells: int = 400_000, costmap: Costmap | None = None, clearance: float = 0.0,
) -> GoalField:
    """The field over the box around the goal, the circles, the costmap and `extent_points` (n, 2), grown by `margin`
    [m].

    `circles` (K, 3) are [x, y, radius] as the path must avoid them (the caller adds any clearance); the costmap's
    lethal cells are kept `clearance` [m] (the robot radius) away from.
    """
    # here, not at the top: scipy.ndimage and scipy.sparse.csgraph cost every planner start ~0.25 s to import, and
    # only goal tasks build a field
    from scipy.ndimage import distance_transform_edt
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    goal = np.asarray(goal, dtype=np.float64)
    circles = np.asarray(circles, dtype=np.float64).reshape(-1, 3)
    pts = [goal[None, :], np.asarray(extent_points, dtype=np.float64).reshape(-1, 2)]
    if circles.shape[0]:
        pts += [circles[:, :2] - circles[:, 2:], circles[:, :2] + circles[:, 2:]]
    if costmap is not None:
        pts.append(costmap.corners())
    allp = np.concatenate(pts)
    lo = allp.min(0) - margin
    size = allp.max(0) + margin - lo
    if size[0] * size[1] / (cell * cell) > max_cells:
        cell = float(np.sqrt(size[0] * size[1] / max_cells))
    w = max(int(np.ceil(size[0] / cell)), 2)
    h = max(int(np.ceil(size[1] / cell)), 2)
    cx = lo[0] + (np.arange(w) + 0.5) * cell
    cy = lo[1] + (np.arange(h) + 0.5) * cell
    gx, gy = np.meshgrid(cx, cy)  # (h, w)
    euclid = np.hypot(gx - goal[0], gy - goal[1])
    blocked = np.zeros((h, w), dtype=bool)
    for ox, oy, r in circles:
        blocked |= (gx - ox) ** 2 + (gy - oy) ** 2 < r * r
    if costmap is not None:
        blocked |= _grid_blocked(costmap, gx, gy, lethal_radius(clearance, costmap.resolution) + 0.5 * math.sqrt(2.0)
                                 * cell)
    free = ~blocked
    visible = free & _segment_clear(gx, gy, goal, circles)
    if costmap is not None:  # paths from the goal's cell and its neighbours only (see the module's note)
        near = np.abs(gx - goal[0]) <= 1.5 * cell
        near &= np.abs(gy - goal[1]) <= 1.5 * cell
        visible &= near

    # graph over free cells plus a virtual source (index n) joined to every visible cell by its exact distance
    n = h * w
    idx = np.arange(n).reshape(h, w)
    rows, cols, wts = [], [], []
    for di, dj in _STENCIL:
        # one move (di rows, dj columns); a move is allowed when both ends are free and so is the cell it
        # passes (for unit steps there is none; for a diagonal or knight move both straddled cells must be free)
        r0 = slice(max(0, -di), h - max(0, di))
        c0 = slice(max(0, -dj), w - max(0, dj))
        r1 = slice(r0.start + di, r0.stop + di)
        c1 = slice(c0.start + dj, c0.stop + dj)
        ok = free[r0, c0] & free[r1, c1]
        if abs(di) + abs(dj) > 1:
            ok &= _straddled_free(free, di, dj, r0, c0)
        rows.append(idx[r0, c0][ok])
        cols.append(idx[r1, c1][ok])
        wts.append(np.full(int(ok.sum()), cell * math.hypot(di, dj)))
    vis = np.flatnonzero(visible.ravel())
    rows.append(np.full(vis.size, n))
    cols.append(vis)
    wts.append(np.maximum(euclid.ravel()[vis], 1e-12))  # zero weights would read as missing edges
    graph = coo_matrix(
        (np.concatenate(wts), (np.concatenate(rows), np.concatenate(cols))), shape=(n + 1, n + 1)
    ).tocsr()
    dist = dijkstra(graph, directed=True, indices=n)[:n].reshape(h, w)
    dist[visible] = euclid[visible]
    reached = np.isfinite(dist) & free
    reachable = bool(reached.any())
    if not reachable:
        dist = euclid.copy()
    else:
        # enclosed free cells: worse than anything reached; blocked cells: their nearest reached cell + the way there
        top = float(dist[reached].max())
        enclosed = free & ~reached
        dist[enclosed] = top + euclid[enclosed]
        inside = ~free
        if inside.any():
            d_in, (ii, jj) = distance_transform_edt(inside, return_indices=True)
            dist[inside] = dist[ii[inside], jj[inside]] + d_in[inside] * cell
    field = np.zeros((h, w, 3))
    field[:, :, 0] = dist
    return GoalField(field, lo, 1.0 / cell, reachable)


def _grid_blocked(costmap: Costmap, gx: np.ndarray, gy: np.ndarray, radius: float) -> np.ndarray:
    """Whether each point (gx, gy) lies within `radius` of a lethal cell's centre (by the grid's distance transform at
    the grid cell the point lies in, less half that cell's diagonal: never short of the true distance)."""
    grid, _frame = costmap.kernel_arrays()
    g = np.floor(costmap.to_grid(np.stack([gx.ravel(), gy.ravel()], axis=1))).astype(np.int64)
    h, w = costmap.shape
    inside = (g[:, 0] >= 0) & (g[:, 0] < w) & (g[:, 1] >= 0) & (g[:, 1] < h)
    d = np.full(g.shape[0], np.inf)
    d[inside] = grid[g[inside, 1], g[inside, 0], 1] - 0.5 * math.sqrt(2.0) * costmap.resolution
    return (d < radius).reshape(gx.shape)


def _straddled_free(free: np.ndarray, di: int, dj: int, r0: slice, c0: slice) -> np.ndarray:
    """For moves longer than one cell: the cells the move's segment passes must be free too."""
    si, sj = int(np.sign(di)), int(np.sign(dj))
    ok = np.ones((r0.stop - r0.start, c0.stop - c0.start), dtype=bool)
    if abs(di) == 1 and abs(dj) == 1:
        passes = [(si, 0), (0, sj)]
    elif abs(di) == 2:  # (2, 1)-type knight move passes (1, 0) and (1, 1)
        passes = [(si, 0), (si, sj)]
    else:  # (1, 2)-type
        passes = [(0, sj), (si, sj)]
    for pi, pj in passes:
        ok &= free[r0.start + pi: r0.stop + pi, c0.start + pj: c0.stop + pj]
    return ok


_FIELDS: Recent[GoalField] = Recent()


def cached_goal_field(
    goal: np.ndarray, circles: np.ndarray, extent_points: np.ndarray, margin: float, cell: float = 0.1,
    costmap: Costmap | None = None, clearance: float = 0.0,
) -> GoalField:
    """`build_goal_field`, remembered for the last few (scene, extent) pairs: keyed by goal, circles, costmap, extent
    points, margin and cell, so that a field is the same whatever was built before it in this process."""
    g = np.ascontiguousarray(goal, dtype=np.float64)
    c = np.ascontiguousarray(circles, dtype=np.float64).reshape(-1, 3)
    e = np.ascontiguousarray(extent_points, dtype=np.float64).reshape(-1, 2)
    key = (g.tobytes(), c.shape, c.tobytes(), e.tobytes(), float(margin), float(cell))
    if costmap is not None:  # (a scene without a grid keeps its key)
        key += (costmap.digest(), float(clearance))
    return _FIELDS.get(key, lambda: build_goal_field(g, c, extent_points, margin, cell, costmap=costmap,
                                                     clearance=clearance))


@njit(cache=True, fastmath=FASTMATH, inline="always")
def goal_distance(field: np.ndarray, origin: np.ndarray, inv_cell: float, x: float, y: float) -> float:
    """Bilinear interpolation of the field's distance; outside the grid, the edge value plus the way to it."""
    r, c, r1, c1, tx, ty, out_c, out_r = grid_cell_at(field, origin, inv_cell, x, y)
    d = (1.0 - ty) * ((1.0 - tx) * field[r, c, 0] + tx * field[r, c1, 0]) + ty * (
        (1.0 - tx) * field[r1, c, 0] + tx * field[r1, c1, 0]
    )
    return d + math.sqrt(out_c * out_c + out_r * out_r) / inv_cell
