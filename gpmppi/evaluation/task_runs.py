"""How the evaluation drives and scores a task of each kind: a lane to follow, a goal to reach.

A `TaskRun` is bound to one task type (as the planner's kinds are, `gpmppi.mppi.task_kinds`) and says, for its tasks:

* `limits`: the closed loop's limits (`ClosedLoopConfig` fields): a lane drives a distance, a goal has a time;
* `stop`: whether a closed loop stops after a cycle (an open lane's end; a goal task's goal or collision);
* `score`: what its runs are scored by (`RunScore` fields): lane RMSE and exits, or reaching the goal;
* `outcome`: what a run shows at its end from its positions alone, with no limits (`gpmppi launch`'s summary).

`run_for(task)` gives the run of a task's kind, or a ValueError for a task of no registered kind (`register` adds one).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np

from gpmppi.evaluation.metrics import (
    first_collision_index,
    goal_outcome,
    lane_end_reached,
    lane_exit_count,
    lane_rmse_mm,
)
from gpmppi.tasks import GoalTask, LaneTask, Task, polyline_length

__all__ = ["GoalRun", "LaneRun", "TaskRun", "register", "run_for"]


class TaskRun(ABC):
    """How a closed loop on a task of one type (`task_type`) is limited, stopped and scored. `cfg` below is the run's
    `ClosedLoopConfig`."""

    task_type: ClassVar[type]

    def __init__(self, task: Task) -> None:
        self.task = task

    @abstractmethod
    def limits(self, lane_distance_m: float, goal_time_limit_s: float) -> dict[str, Any]:
        """The closed loop's limits for this task (`ClosedLoopConfig` fields)."""

    def stop(self, true_state: np.ndarray, driven_m: float, cfg: Any) -> str | None:  # noqa: ANN401
        """The run's status if it stops after reaching `true_state` having driven `driven_m`, else None."""
        return None

    @abstractmethod
    def score(self, positions: np.ndarray, times: np.ndarray, status: str, cfg: Any) -> dict[str, Any]:  # noqa: ANN401
        """The task's own scores of a run (`RunScore` fields) from its true positions (T+1, 2) at `times`."""

    def outcome(self, positions: np.ndarray) -> tuple[dict[str, Any], str]:
        """A run's outcome from its positions (T, 2) alone, by name, and in one line (`Summary` fields)."""
        return {}, type(self.task).__name__


_RUNS: dict[type, type[TaskRun]] = {}


def register(run: type[TaskRun]) -> type[TaskRun]:
    """Make `run` the evaluation of its `task_type`'s tasks (a class decorator)."""
    _RUNS[run.task_type] = run
    return run


def run_for(task: Task) -> TaskRun:
    """The evaluation of `task`, or a ValueError that names the task types it can evaluate."""
    run = _RUNS.get(type(task))
    if run is None:
        names = " or ".join(t.__name__ for t in _RUNS)
        raise ValueError(f"the evaluation runs a {names}, got {type(task).__name__} "
                         "(register a gpmppi.evaluation.task_runs.TaskRun for it)")
    return run(task)


@register
class LaneRun(TaskRun):
    """A lane: driven for a distance; an open lane's end stops it (`finished`); scored by RMSE and lane exits."""

    task_type = LaneTask
    task: LaneTask

    def __init__(self, task: LaneTask) -> None:
        super().__init__(task)
        self.open_length = 0.0 if task.closed else polyline_length(task.centerline, closed=False)

    def limits(self, lane_distance_m: float, goal_time_limit_s: float) -> dict[str, Any]:
        speed = max(self.task.speed_target, 0.25)
        # an open lane ends (status `finished`) at its last point, which may come before the distance limit
        target = lane_distance_m if self.task.closed else min(lane_distance_m, self.open_length)
        return {"time_limit_s": 1.5 * target / speed + 10.0, "distance_limit_m": lane_distance_m,
                "stop_on_collision": False}

    def stop(self, true_state: np.ndarray, driven_m: float, cfg: Any) -> str | None:  # noqa: ANN401
        t = self.task
        if t.closed or not cfg.stop_at_lane_end:  # closed lanes have no end
            return None
        if driven_m >= 0.5 * self.open_length and lane_end_reached(
                true_state[None, :2], t.centerline, t.half_width, cfg.lane_end_tolerance_m)[0]:
            return "finished"
        return None

    def score(self, positions: np.ndarray, times: np.ndarray, status: str, cfg: Any) -> dict[str, Any]:  # noqa: ANN401
        t = self.task
        exits = lane_exit_count(positions, t.centerline, t.half_width, t.closed)
        return {"rmse_mm": lane_rmse_mm(positions, t.centerline, t.closed), "lane_exits": exits,
                "success": status in ("distance", "finished") and exits == 0}

    def outcome(self, positions: np.ndarray) -> tuple[dict[str, Any], str]:
        t = self.task
        rmse = lane_rmse_mm(positions, t.centerline, t.closed)
        exits = lane_exit_count(positions, t.centerline, t.half_width, t.closed)
        return {"lane_rmse_mm": rmse, "lane_exits": exits}, f"lane, RMSE to centre {rmse:.0f} mm, lane exits {exits}"


@register
class GoalRun(TaskRun):
    """A goal among circles: a time limit; reaching the goal or hitting a circle stops it; scored by the outcome."""

    task_type = GoalTask
    task: GoalTask

    def limits(self, lane_distance_m: float, goal_time_limit_s: float) -> dict[str, Any]:
        return {"time_limit_s": goal_time_limit_s}

    def stop(self, true_state: np.ndarray, driven_m: float, cfg: Any) -> str | None:  # noqa: ANN401
        t = self.task
        hit = first_collision_index(true_state[None, :2], t.obstacles, cfg.robot_radius, t.costmap)
        if cfg.stop_on_collision and hit is not None:
            return "collision"
        if cfg.stop_at_goal and np.linalg.norm(true_state[:2] - t.goal) <= t.tolerance:
            return "goal"
        return None

    def score(self, positions: np.ndarray, times: np.ndarray, status: str, cfg: Any) -> dict[str, Any]:  # noqa: ANN401
        t = self.task
        out = goal_outcome(times, positions, t.goal, t.tolerance, t.obstacles, cfg.time_limit_s, cfg.robot_radius,
                           t.costmap)
        return {"success": out.success, "time_to_goal_s": out.time_to_goal_s, "min_clearance_m": out.min_clearance_m}

    def outcome(self, positions: np.ndarray) -> tuple[dict[str, Any], str]:
        d = np.linalg.norm(positions - self.task.goal[None, :], axis=1)
        reached, last = bool(np.any(d <= self.task.tolerance)), float(d[-1])
        return ({"goal_reached": reached, "final_goal_distance_m": last},
                f"goal, reached {reached}, final distance {last:.2f} m")
