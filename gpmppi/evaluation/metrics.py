"""Scores of closed-loop runs: lane RMSE, lane exits, the open-lane end, obstacle clearance, success and
time-to-goal, command smoothness and terrain-weight quality.

Everything here is plain numpy on arrays (positions (T, 2), times (T,)), so it can be checked in
closed form on hand-made trajectories.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpmppi.costmap import Costmap
from gpmppi.tasks import distance_to_polyline, polyline_length, progress_along_polyline

# [s] terrain weights are scored after this much of a run: the estimator starts from uniform weights and needs a
# history of transitions before its answer means anything
WEIGHT_SETTLE_S = 3.0


def lane_rmse_mm(points: np.ndarray, centerline: np.ndarray, closed: bool = True) -> float:
    """Root-mean-square distance to the lane centre line, in millimetres."""
    d = distance_to_polyline(points, centerline, closed)
    return float(np.sqrt(np.mean(d * d)) * 1000.0) if d.size else float("nan")


def lane_exit_count(points: np.ndarray, centerline: np.ndarray, half_width: float, closed: bool = True) -> int:
    """How many times the robot's centre leaves the lane (transitions inside -> outside; starting outside counts)."""
    outside = distance_to_polyline(points, centerline, closed) > half_width
    if outside.size == 0:
        return 0
    return int(outside[0]) + int(np.count_nonzero(outside[1:] & ~outside[:-1]))


def lane_end_reached(
    points: np.ndarray, centerline: np.ndarray, half_width: float, tolerance_m: float = 0.5
) -> np.ndarray:
    """Whether each point (T, 2) has reached the end of an open lane: in the lane, its closest centre-line point
    within `tolerance_m` [m] of the last point along the lane.

    Past the end the closest point is the end point itself, so a robot that overshoots counts as arrived too (while
    it is within `half_width` of the end); a robot beside the lane (farther than `half_width` from the centre line)
    never counts.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if p.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    along = progress_along_polyline(p, centerline, closed=False)
    inside = distance_to_polyline(p, centerline, closed=False) <= half_width
    return inside & (along >= polyline_length(centerline, closed=False) - tolerance_m)


def obstacle_clearance(
    points: np.ndarray, obstacles: np.ndarray, robot_radius: float = 0.0, costmap: Costmap | None = None,
) -> np.ndarray:
    """Clearance (T,) [m] from the robot's disc to the nearest obstacle circle or lethal cell of `costmap` (negative =
    overlap; `Costmap.clearance`); inf if none."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    o = np.asarray(obstacles, dtype=np.float64).reshape(-1, 3)
    out = np.full(p.shape[0], np.inf)
    if o.shape[0]:
        out = (np.linalg.norm(p[:, None, :] - o[None, :, :2], axis=2) - o[None, :, 2] - robot_radius).min(axis=1)
    if costmap is not None and p.shape[0]:
        out = np.minimum(out, costmap.clearance(p, robot_radius))
    return out


def first_collision_index(
    points: np.ndarray, obstacles: np.ndarray, robot_radius: float = 0.0, costmap: Costmap | None = None,
) -> int | None:
    """Index of the first sample where the robot overlaps an obstacle, or None."""
    hit = np.flatnonzero(obstacle_clearance(points, obstacles, robot_radius, costmap) < 0.0)
    return int(hit[0]) if hit.size else None


def first_goal_index(points: np.ndarray, goal: np.ndarray, tolerance: float) -> int | None:
    """Index of the first sample within `tolerance` of `goal`, or None."""
    d = np.linalg.norm(np.asarray(points, dtype=np.float64).reshape(-1, 2) - np.asarray(goal)[None, :2], axis=1)
    hit = np.flatnonzero(d <= tolerance)
    return int(hit[0]) if hit.size else None


def path_length(points: np.ndarray) -> float:
    """Length [m] of the driven path."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) if p.shape[0] > 1 else 0.0


@dataclass(frozen=True)
class GoalOutcome:
    """Result of one goal-reaching run."""

    success: bool  # goal reached within tolerance, before the time limit, with no collision before it
    collided: bool  # overlapped an obstacle before reaching the goal (or at all, if the goal was never reached)
    time_to_goal_s: float  # time of the first sample within tolerance (nan if never)
    min_clearance_m: float  # smallest clearance up to the goal (or the whole run)


def goal_outcome(
    times: np.ndarray,
    points: np.ndarray,
    goal: np.ndarray,
    tolerance: float,
    obstacles: np.ndarray,
    time_limit: float,
    robot_radius: float = 0.0,
    costmap: Costmap | None = None,
) -> GoalOutcome:
    """Score a goal-reaching run: success needs the goal within `time_limit` and no collision before it."""
    t = np.asarray(times, dtype=np.float64) - float(times[0])
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    g = first_goal_index(p, goal, tolerance)
    if g is not None and t[g] > time_limit:
        g = None
    end = p.shape[0] if g is None else g + 1
    clear = obstacle_clearance(p[:end], obstacles, robot_radius, costmap)
    collided = bool(np.any(clear < 0.0))
    success = g is not None and not collided
    return GoalOutcome(
        success=success,
        collided=collided,
        time_to_goal_s=float(t[g]) if g is not None else float("nan"),
        min_clearance_m=float(clear.min()) if clear.size else float("inf"),
    )


def mean_std(values: np.ndarray | list[float]) -> tuple[float, float]:
    """Mean and population standard deviation of the finite values (nan, nan if there are none)."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("nan"), float("nan")
    return float(v.mean()), float(v.std())


# --- command smoothness and terrain weights ------------------------------------------------------------------------


def command_rates(times: np.ndarray, commands: np.ndarray) -> np.ndarray:
    """|change of each command component| / time between consecutive commands (T-1, C): for [v_ref, omega_ref]
    in m/s^2 and rad/s^2.

    `times` (T,) are the commands' times (a trajectory's times (T+1,) may be passed: the first T are used). Fewer
    than 2 commands give an empty (0, C) array, whose `mean_p95` is (nan, nan).
    """
    u = np.asarray(commands, dtype=np.float64)
    u = u[:, None] if u.ndim == 1 else u  # one command component given as (T,)
    if u.ndim != 2:
        raise ValueError(f"command_rates: commands must be (T, C), got shape {u.shape}")
    t = np.asarray(times, dtype=np.float64).reshape(-1)[: u.shape[0]]
    if t.size != u.shape[0]:
        raise ValueError(f"command_rates: {u.shape[0]} commands but {t.size} times")
    if u.shape[0] < 2:
        return np.zeros((0, u.shape[1]))
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise ValueError("command_rates: command times must increase")
    return np.abs(np.diff(u, axis=0)) / dt[:, None]


def mean_p95(values: np.ndarray) -> tuple[float, float]:
    """Mean and 95th percentile (numpy's linear interpolation) of `values`; (nan, nan) if there are none."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0:
        return float("nan"), float("nan")
    return float(v.mean()), float(np.percentile(v, 95))


def _settled_spans(times: np.ndarray, settle_s: float) -> np.ndarray:
    """(T,) the seconds of each cycle [times[k], times[k + 1]) after the first `settle_s` of the run."""
    return np.clip(times[1:] - np.maximum(times[:-1], times[0] + settle_s), 0.0, None)


def true_weight_mean(
    times: np.ndarray,
    weights: np.ndarray,
    driven: list[str],
    terrain_names: list[str],
    settle_s: float = WEIGHT_SETTLE_S,
) -> float | None:
    """Time-averaged weight the estimate gave the terrain actually under the robot, after the first `settle_s`.

    `times` (T+1,) are the cycle boundaries: the weights `weights[k]` (T, M) (in `terrain_names` order) were used and
    the robot drove on `driven[k]` from times[k] to times[k+1]. Time on a terrain the model does not know (not in
    `terrain_names`, e.g. sand) is left out, as it has no "true" weight. None when there is nothing to average: no
    weights, no time after `settle_s` (a run shorter than that), or all of it on unknown terrain.
    """
    w = np.asarray(weights, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if w.ndim != 2 or w.shape[0] == 0 or w.shape[1] == 0:
        return None
    if t.size != w.shape[0] + 1 or len(driven) != w.shape[0]:
        raise ValueError(f"true_weight_mean: {w.shape[0]} weight rows need {w.shape[0] + 1} times and as many "
                         f"terrains, got {t.size} times and {len(driven)} terrains")
    index = {name: i for i, name in enumerate(terrain_names)}
    span = _settled_spans(t, settle_s)
    known = np.array([name in index for name in driven])
    span = np.where(known, span, 0.0)
    total = float(span.sum())
    if total <= 0.0:
        return None
    true_w = np.array([w[k, index[name]] if name in index else 0.0 for k, name in enumerate(driven)])
    return float(np.sum(true_w * span) / total)


def weight_switches_per_min(
    times: np.ndarray, weights: np.ndarray, settle_s: float = WEIGHT_SETTLE_S, identified: np.ndarray | None = None
) -> float | None:
    """How often the terrain with the largest weight (argmax; ties go to the first) changes, per minute of run after
    the first `settle_s` (as `true_weight_mean`: the weights start uniform, so the first answer is no switch).

    `times` (T+1,) are the cycle boundaries of the weights (T, M): row k holds from times[k], so a change between
    rows k-1 and k happens at times[k] and counts when times[k] >= times[0] + settle_s; the minutes are those from
    times[0] + settle_s to times[-1]. None when there are no weights or no time after `settle_s`.

    `identified` (T,) (None or empty: every row) says which rows name a top ground (`TerrainEstimate.identified`):
    a row that names none has no top, so a change is counted between consecutive rows that name one (the first
    identification, after rows naming none, is no change; the rows naming none are skipped, not a top of their own).
    """
    w = np.asarray(weights, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if w.ndim != 2 or w.shape[0] == 0 or w.shape[1] == 0 or t.size < 2:
        return None
    if t.size != w.shape[0] + 1:
        raise ValueError(f"weight_switches_per_min: {w.shape[0]} weight rows need {w.shape[0] + 1} times, got "
                         f"{t.size}")
    start = float(t[0]) + settle_s
    minutes = (float(t[-1]) - start) / 60.0
    if minutes <= 0.0:
        return None
    top = np.argmax(w, axis=1)
    if identified is not None and np.size(identified):
        named = np.asarray(identified, dtype=bool).reshape(-1)
        if named.size != w.shape[0]:
            raise ValueError(f"weight_switches_per_min: {w.shape[0]} weight rows need as many identified flags, got "
                             f"{named.size}")
        rows = np.flatnonzero(named)  # the rows with a top; a change k -> j at times[j]
        changed_at = t[rows[1:]][top[rows[1:]] != top[rows[:-1]]]
        return float(np.count_nonzero(changed_at >= start - 1e-9)) / minutes
    changed = top[1:] != top[:-1]  # change k-1 -> k at times[k]
    return float(np.count_nonzero(changed & (t[1:-1] >= start - 1e-9))) / minutes


def unidentified_share(
    times: np.ndarray, identified: np.ndarray, settle_s: float = WEIGHT_SETTLE_S
) -> float | None:
    """The share of the run after the first `settle_s` whose weights named no top ground (`identified` (T,) False
    on the rows of the cycle boundaries `times` (T+1,)). None when there are no rows or no time after `settle_s`."""
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    named = np.asarray(identified, dtype=bool).reshape(-1)
    if named.size == 0 or t.size != named.size + 1:
        return None
    span = _settled_spans(t, settle_s)
    total = float(span.sum())
    return float(np.sum(span[~named]) / total) if total > 0.0 else None


def top_terrain_confusion(
    runs: list[tuple[str, np.ndarray, np.ndarray]], names: list[str], settle_s: float = WEIGHT_SETTLE_S
) -> tuple[list[str], np.ndarray]:
    """The terrain estimator's confusion: per true terrain (rows, those among `names` that some run drove on, in
    `names` order) the fraction of time after the first `settle_s` that each of `names` (columns) had the largest
    weight.

    `runs` holds per run its true terrain, the cycle boundaries `times` (T+1,) and the weights (T, M), row k holding
    from times[k] to times[k + 1] (as `true_weight_mean`). Rows sum to 1; a run with no time after `settle_s` adds
    nothing, and a true terrain without any such time is left out.
    """
    rows: dict[str, np.ndarray] = {}
    for terrain, times, weights in runs:
        w = np.asarray(weights, dtype=np.float64)
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        if terrain not in names or w.ndim != 2 or w.shape[1] != len(names) or t.size != w.shape[0] + 1:
            continue
        held = _settled_spans(t, settle_s)
        if held.sum() <= 0.0:
            continue
        acc = rows.setdefault(terrain, np.zeros(len(names)))
        np.add.at(acc, np.argmax(w, axis=1), held)
    order = [n for n in names if n in rows]
    if not order:
        return [], np.zeros((0, len(names)))
    matrix = np.stack([rows[n] / rows[n].sum() for n in order])
    return order, matrix


def unknown_share(times: np.ndarray, unknown: np.ndarray, driven: list[str], terrain_names: list[str],
                  level: float = 0.5, new_ground: bool = False) -> float | None:
    """Share of the time on trained grounds (`driven[k]` in `terrain_names`) during which P(unknown) `unknown[k]`
    (T,) was above `level`: the test's false alarms. None without time on a trained ground or without values.
    `new_ground`: the same share of the time on grounds *not* in `terrain_names` (how much of it was flagged)."""
    u = np.asarray(unknown, dtype=np.float64).reshape(-1)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if u.size == 0 or t.size != u.size + 1 or len(driven) != u.size:
        return None
    span = np.diff(t) * np.array([(name in terrain_names) != new_ground for name in driven])
    total = float(span.sum())
    return float(span[u > level].sum() / total) if total > 0 else None


def unknown_delay_s(times: np.ndarray, unknown: np.ndarray, driven: list[str], terrain_names: list[str],
                    level: float = 0.5) -> float | None:
    """Seconds from the start of the first stretch on a ground not in `terrain_names` until P(unknown) `unknown[k]`
    first exceeds `level` on it (inf when it never does there); None without such a stretch."""
    u = np.asarray(unknown, dtype=np.float64).reshape(-1)
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    new = np.array([name not in terrain_names for name in driven], dtype=bool)
    if u.size == 0 or not new.any():
        return None
    start = int(np.argmax(new))
    end = start + (int(np.argmin(new[start:])) if not new[start:].all() else int(new[start:].size))
    hits = np.flatnonzero(u[start:end] > level)
    return float(t[start + hits[0]] - t[start]) if hits.size else float("inf")
