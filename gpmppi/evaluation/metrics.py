"""Scores of closed-loop runs: lane RMSE, lane exits, obstacle clearance, success and time-to-goal.

Everything here is plain numpy on arrays (positions (T, 2), times (T,)), so it can be checked in
closed form on hand-made trajectories.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpmppi.tasks import distance_to_polyline


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


def obstacle_clearance(points: np.ndarray, obstacles: np.ndarray, robot_radius: float = 0.0) -> np.ndarray:
    """Clearance (T,) [m] from the robot's disc to the nearest obstacle circle (negative = overlap); inf if none."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    o = np.asarray(obstacles, dtype=np.float64).reshape(-1, 3)
    if o.shape[0] == 0:
        return np.full(p.shape[0], np.inf)
    d = np.linalg.norm(p[:, None, :] - o[None, :, :2], axis=2) - o[None, :, 2] - robot_radius
    return d.min(axis=1)


def first_collision_index(points: np.ndarray, obstacles: np.ndarray, robot_radius: float = 0.0) -> int | None:
    """Index of the first sample where the robot overlaps an obstacle, or None."""
    hit = np.flatnonzero(obstacle_clearance(points, obstacles, robot_radius) < 0.0)
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
) -> GoalOutcome:
    """Score a goal-reaching run: success needs the goal within `time_limit` and no collision before it."""
    t = np.asarray(times, dtype=np.float64) - float(times[0])
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    g = first_goal_index(p, goal, tolerance)
    if g is not None and t[g] > time_limit:
        g = None
    end = p.shape[0] if g is None else g + 1
    clear = obstacle_clearance(p[:end], obstacles, robot_radius)
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
