"""The geometry of the view, shared by every viewer: rerun (`rerun_map`) and Foxglove (`foxglove_scene`) both draw
what these functions compute from our messages, and only translate it into their own types.

- pure geometry (numpy only): circles, covariance ellipses, lane offsets, the tightened lane along the plan horizon,
  the robot's outline, and a cost colour ramp;
- the map's layers and their style (`LAYERS`: colour, line radius [m], draw order), one table for both viewers;
- per message, what is drawn: what the task's kind outlines (`gpmppi.tasks.TaskOutline`: a lane's edges and centre,
  circles, a goal), the plan's covariance ellipses, its bounds as the kind says what they are (a lane's tightened
  half-widths or the circles' inflation), and the decimated rollouts with their cost colours.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpmppi.tasks import TaskOutline
from schemas import OccupancyGrid, Plan

# the robot drawn as a footprint with a pointed nose (so its heading reads at a glance), body frame [m]:
# about a Jackal's 0.51 m x 0.43 m
ROBOT_OUTLINE = np.array([[-0.25, -0.215], [0.17, -0.215], [0.32, 0.0], [0.17, 0.215], [-0.25, 0.215], [-0.25, -0.215]])

# cost ramp, low -> high: teal, yellow, red (RGBA; rollouts are drawn half-transparent so the plan shows through)
_RAMP = np.array([[20, 170, 150, 150], [235, 200, 40, 130], [215, 50, 50, 110]], dtype=np.float64)


def circle(x: float, y: float, r: float, n: int = 48) -> np.ndarray:
    """(n+1) x 2 closed polyline of a circle of radius r [m] about (x, y)."""
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    return np.stack([x + r * np.cos(a), y + r * np.sin(a)], axis=1)


def ellipse(cx: float, cy: float, sxx: float, sxy: float, syy: float, n_sigma: float = 2.0, n: int = 16) -> np.ndarray:
    """Closed polyline of the n_sigma ellipse of a 2-D position covariance [m^2] about (cx, cy)."""
    cov = np.array([[sxx, sxy], [sxy, syy]])
    vals, vecs = np.linalg.eigh(cov)
    vals = np.clip(vals, 0.0, None)
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    unit = np.stack([np.cos(a), np.sin(a)], axis=1)
    return np.array([cx, cy]) + n_sigma * (unit * np.sqrt(vals)) @ vecs.T


def ellipses(centres: np.ndarray, covs: np.ndarray, n_sigma: float = 2.0, n: int = 16) -> np.ndarray:
    """K x (n+1) x 2 closed polylines of the n_sigma ellipses of K position covariances [sxx, sxy, syy] [m^2]
    about K centres (a 2 x 2 eigen-decomposition in closed form, for all at once)."""
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    sxx, sxy, syy = np.asarray(covs, dtype=np.float64).reshape(-1, 3).T
    mean, diff = (sxx + syy) / 2, np.sqrt(((sxx - syy) / 2) ** 2 + sxy**2)
    l1, l2 = np.clip(mean + diff, 0.0, None), np.clip(mean - diff, 0.0, None)
    angle = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # of the major axis
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    u, v = n_sigma * np.sqrt(l1)[:, None] * np.cos(a), n_sigma * np.sqrt(l2)[:, None] * np.sin(a)
    ca, sa = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return np.stack([c[:, :1] + u * ca - v * sa, c[:, 1:] + u * sa + v * ca], axis=2)


def offset(polyline: np.ndarray, distance: np.ndarray | float, closed: bool) -> np.ndarray:
    """The polyline shifted left by `distance` [m] (per vertex or constant) along its normals (closed: the first
    point is repeated at the end)."""
    p = np.asarray(polyline, dtype=np.float64)
    nxt = np.roll(p, -1, axis=0) if closed else np.vstack([p[1:], 2 * p[-1] - p[-2]])
    prv = np.roll(p, 1, axis=0) if closed else np.vstack([2 * p[0] - p[1], p[:-1]])
    t = nxt - prv
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    normal = np.stack([-t[:, 1], t[:, 0]], axis=1)
    out = p + normal * np.reshape(distance, (-1, 1))
    return np.vstack([out, out[:1]]) if closed else out


def closed_polyline(points: np.ndarray, closed: bool) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    return np.vstack([p, p[:1]]) if closed else p


def project_to_lane(points: np.ndarray, centerline: np.ndarray, closed: bool) -> tuple[np.ndarray, np.ndarray]:
    """For each point, its nearest point on the centre polyline and the lane's left unit normal there (searched
    on the two segments next to the nearest vertex: exact for lanes whose turns are wider than the lane)."""
    c = np.asarray(centerline, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    m = len(c)
    d2 = ((p[:, None, :] - c[None]) ** 2).sum(axis=2)  # P x M
    v = np.argmin(d2, axis=1)
    starts = np.stack([v - 1, v], axis=1)  # the segments ending and starting at the nearest vertex
    starts = starts % m if closed else np.clip(starts, 0, m - 2)
    a, b = c[starts], c[(starts + 1) % m]  # P x 2 x 2
    seg = b - a
    seg_len2 = np.maximum((seg**2).sum(axis=2), 1e-12)
    t = np.clip(((p[:, None, :] - a) * seg).sum(axis=2) / seg_len2, 0.0, 1.0)
    foot = a + t[..., None] * seg
    best = np.argmin(((foot - p[:, None, :]) ** 2).sum(axis=2), axis=1)
    rows = np.arange(len(p))
    tangent = seg[rows, best] / np.sqrt(seg_len2[rows, best])[:, None]
    return foot[rows, best], np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)


def tightened_bounds(
    states_xy: np.ndarray, half_widths: np.ndarray, centerline: np.ndarray, closed: bool
) -> list[np.ndarray]:
    """The tightened lane bounds where the plan uses them: at each plan step's nearest centre point, the
    tightened half-width [m] to either side (two polylines, left and right)."""
    n = min(len(states_xy), len(half_widths))
    if n < 2:
        return []
    foot, normal = project_to_lane(np.asarray(states_xy)[:n], centerline, closed)
    r = np.asarray(half_widths, dtype=np.float64)[:n, None]
    return [foot + normal * r, foot - normal * r]


def robot_outline(x: float, y: float, theta: float) -> np.ndarray:
    """The robot's outline in the map frame at pose (x, y, theta)."""
    c, s = np.cos(theta), np.sin(theta)
    rot = np.array([[c, -s], [s, c]])
    return ROBOT_OUTLINE @ rot.T + np.array([x, y])


def cost_colors(costs: np.ndarray) -> np.ndarray:
    """RGBA per rollout by cost rank (rank, not value: costs span decades once an indicator term fires)."""
    costs = np.asarray(costs, dtype=np.float64)
    n = costs.size
    if n == 0:
        return np.zeros((0, 4), dtype=np.uint8)
    finite = np.where(np.isfinite(costs), costs, np.inf)
    u = np.empty(n)
    u[np.argsort(finite, kind="stable")] = np.linspace(0.0, 1.0, n) if n > 1 else [0.0]
    x = u * (len(_RAMP) - 1)
    i = np.minimum(x.astype(int), len(_RAMP) - 2)
    f = (x - i)[:, None]
    return np.round(_RAMP[i] * (1 - f) + _RAMP[i + 1] * f).astype(np.uint8)


def pack_rgba(colors: np.ndarray) -> np.ndarray:
    """N x 4 uint8 RGBA as N packed 0xRRGGBBAA uint32 (rerun takes these without conversion)."""
    c = np.asarray(colors, dtype=np.uint32)
    return (c[:, 0] << 24) | (c[:, 1] << 16) | (c[:, 2] << 8) | c[:, 3]


# ---- the map's layers, bottom to top ---------------------------------------------------------------------
@dataclass(frozen=True)
class Layer:
    """How one map layer is drawn: its colour (RGB or RGBA, 0-255; None: per element), its line radius [m]
    (half the line's width; None: not a line) and its draw order (higher is on top)."""

    color: tuple[int, ...] | None
    radius: float | None
    order: float


LAYERS: dict[str, Layer] = {
    "edges": Layer((50, 50, 50), 0.06, 10.0),
    "centre": Layer((160, 160, 160), 0.02, 11.0),
    "tightened": Layer((240, 180, 0), 0.05, 12.0),
    "inflated": Layer((255, 120, 120), 0.03, 13.0),
    "obstacles": Layer((200, 40, 40, 220), None, 14.0),
    "costmap": Layer((200, 40, 40, 160), None, 9.0),  # a grid's lethal cells, under the lane and the plans
    "goal": Layer((30, 170, 30), 0.05, 15.0),
    "samples": Layer(None, 0.02, 20.0),
    "covariance": Layer((150, 60, 220), 0.02, 25.0),
    "nominal": Layer((255, 140, 0), 0.06, 30.0),
    "path": Layer((0, 60, 200), 0.05, 40.0),
    "robot": Layer((200, 0, 110), 0.05, 50.0),  # magenta: apart from the blue path, the orange plan and the grey lane
}


@dataclass
class Decimation:
    """How much per-plan data is drawn (the big part of a recording), the same in every viewer."""

    samples_every: int = 2  # draw the rollouts of every n-th plan
    max_samples: int = 32  # at most this many rollouts of a plan
    sample_stride: int = 2  # every n-th point along a rollout
    ellipse_every: int = 8  # every n-th covariance ellipse of the plan
    path_chunk: int = 50  # driven-path states per strip


# ---- per message: what is drawn -----------------------------------------------------------------------------
def lethal_cells(grid: OccupancyGrid) -> tuple[np.ndarray, float]:
    """The world positions (n, 2) [m] of a grid's lethal cells' centres (in its header's frame) and the radius [m] to
    draw each with (half a cell)."""
    values = np.asarray(grid.data, dtype=np.int64).reshape(grid.height, grid.width)
    rows, cols = np.nonzero(values >= grid.lethal)
    gx, gy = (cols + 0.5) * grid.resolution, (rows + 0.5) * grid.resolution
    c, s = np.cos(grid.origin_yaw), np.sin(grid.origin_yaw)
    return np.stack([grid.origin_x + c * gx - s * gy, grid.origin_y + s * gx + c * gy], axis=1), 0.5 * grid.resolution


def task_lines(outline: TaskOutline) -> dict[str, tuple[str, list[np.ndarray]]]:
    """The lines of what a task's kind outlines (`Task.outline()`), by entity (`TASK_ENTITIES`): (layer, polylines):
    a lane's two edges (centre +- half-width) and its centre (closed where the lane is), a goal's tolerance circle."""
    out: dict[str, tuple[str, list[np.ndarray]]] = {}
    if outline.lane is not None:
        c, hw = outline.lane, outline.half_width
        out["lane/edges"] = ("edges", [offset(c, hw, outline.closed), offset(c, -hw, outline.closed)])
        out["lane/centre"] = ("centre", [closed_polyline(c, outline.closed)])
    if outline.goal is not None:
        out["goal"] = ("goal", [circle(outline.goal[0], outline.goal[1], outline.tolerance)])
    return out


# every entity a task may draw (`task_lines`, and "obstacles" for its circles): a new task clears those it does not
TASK_ENTITIES = ("lane/edges", "lane/centre", "goal", "obstacles")


def plan_states(plan: Plan) -> np.ndarray | None:
    """The nominal plan's states (K x 5), or None when there is no line to draw (fewer than two)."""
    states = np.asarray(plan.states, dtype=np.float64)
    return states if states.ndim == 2 and states.shape[0] >= 2 else None


def plan_ellipses(plan: Plan, states: np.ndarray, every: int) -> np.ndarray | None:
    """2-sigma position ellipses of every `every`-th plan step from step `every` on (step 0 is the known start, no
    spread) and always the horizon's end; None without covariances."""
    if not plan.cov_xy:
        return None
    n = min(len(plan.cov_xy), len(states))
    ks = sorted({*range(every, n, every), n - 1})
    return ellipses(states[ks, :2], np.asarray(plan.cov_xy, dtype=np.float64)[ks])


def tightening(plan: Plan) -> tuple[float, float] | None:
    """The tightened half-width (lane) or inflation (obstacles) at step 1 and at the last step [m]."""
    if not plan.tightened:
        return None
    tightened = plan.tightened
    return float(tightened[min(1, len(tightened) - 1)]), float(tightened[-1])


def plan_bounds(plan: Plan, states: np.ndarray, outline: TaskOutline) -> tuple[str, list[np.ndarray]]:
    """What a plan's per-step bounds (`Plan.tightened`) draw, by what the task's kind says they are (`bounds`), as
    (layer, polylines): a lane's tightened half-width either side of its centre, per step of the horizon, where the
    plan is ("tightened"); or the circles grown by the plan's largest inflation ("inflated"). Empty without bounds."""
    tightened = np.asarray(plan.tightened, dtype=np.float64)
    if outline.bounds == "half_width" and outline.lane is not None:
        if tightened.size == 0:
            return "tightened", []
        steps = tightened if len(tightened) == len(states) else np.resize(tightened, len(states))
        return "tightened", tightened_bounds(states[:, :2], steps, outline.lane, outline.closed)
    if tightened.size == 0 or outline.circles.shape[0] == 0:
        return "inflated", []
    inflation = float(np.max(tightened))
    return "inflated", [circle(x, y, r + inflation) for x, y, r in outline.circles]


def rollouts(plan: Plan, max_samples: int, stride: int) -> tuple[np.ndarray, np.ndarray] | None:
    """At most `max_samples` sampled rollouts (k x m x 2, float32, every `stride`-th point and the last) and their
    RGBA colours by cost rank (k x 4, uint8); None without samples."""
    if not plan.samples or max_samples <= 0:
        return None
    k = min(len(plan.samples), max_samples)
    costs = np.asarray(plan.sample_costs[:k] if len(plan.sample_costs) >= k else np.zeros(k))
    points = np.asarray(plan.samples[:k], dtype=np.float32)
    keep = np.unique(np.r_[np.arange(0, points.shape[1], stride), points.shape[1] - 1])
    return points[:, keep], cost_colors(costs)


def rollout_cost_summary(plan: Plan) -> tuple[float, float] | None:
    """The minimum and median of the finite rollout costs, or None."""
    if not plan.sample_costs:
        return None
    costs = np.asarray(plan.sample_costs, dtype=np.float64)
    finite = costs[np.isfinite(costs)]
    return (float(finite.min()), float(np.median(finite))) if finite.size else None


class PathStrips:
    """The driven path as strips of `chunk` states, each strip starting where the previous one ended: `add`
    returns (strip index, the growing strip's points), so a viewer re-sends only the strip that grows and a state
    costs at most `chunk` points, whatever the run's length."""

    def __init__(self, chunk: int) -> None:
        self.chunk = chunk
        self.index = 0
        self.points: list[list[float]] = []

    def add(self, x: float, y: float) -> tuple[int, list[list[float]]]:
        if len(self.points) >= self.chunk:
            self.index += 1
            self.points = self.points[-1:]
        self.points.append([x, y])
        return self.index, self.points
