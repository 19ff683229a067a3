"""Task kinds: what the planner does differently for a lane to follow and a goal to reach.

A kind is a class bound to one task type (`LaneTask`, `GoalTask`); the planner holds one instance of each kind it has
been given a task of. Each owns, for its tasks:

* its checks of a task against the planner's configuration (`check`);
* its chance-constrained bounds from the propagated covariances (`bounds`: tightened lane half-widths, or inflated
  obstacle radii) and the name of the flag that counts their clamps (`clamp_flag`);
* the kernels' task input (`task_bundle`, with what it caches per task: the lane lookup, the goal field);
* one number a step of its bounds, for a plan message (`per_step`);
* a bound on its commanded speed below the planner's (`speed_limit`: a goal's while the ground is unknown);
* its critic chain: the registered critics of a kernel task kind (`critics`, a key of `critics.base.TASK_KINDS`), as
  the cost bundle the kernels read (`cost`), and the sampling noise of its rollouts (`noise_std`).

A new kind is a `TaskKind` subclass registered with `register` (`tests/test_task_kinds.py` plugs in a toy one). A
task whose type has no registered kind is refused with a `ValueError` naming the kinds there are
(`kind_class_for`): it never falls to another kind's critics.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np

from gpmppi.costmap import lethal_radius
from gpmppi.mppi.bundles import CostBundle, TaskBundle
from gpmppi.mppi.config import PlannerConfig
from gpmppi.mppi.costs import ChanceQuantiles, inflate_grid, inflate_obstacles, tighten_lane
from gpmppi.mppi.critics.base import TASK_KINDS
from gpmppi.mppi.goal_field import GoalField, cached_goal_field
from gpmppi.mppi.lane import LaneLookup, cached_lane_lookup
from gpmppi.tasks import GoalTask, LaneTask

__all__ = ["GoalKind", "LaneKind", "TaskKind", "kind_class_for", "register", "registered_kinds"]


class TaskKind(ABC):
    """What the planner does for the tasks of one type (`task_type`): checks, bounds, the kernels' task input and
    critic chain. One instance per planner (it may cache per task); `reset` with the planner's."""

    task_type: ClassVar[type]  # the task dataclass this kind plans for
    critics: ClassVar[str]  # the kernels' task kind whose critics score it (a key of `critics.base.TASK_KINDS`)
    clamp_flag: ClassVar[str]  # `PlanResult.flags` key of the bounds' clamps (and that key + "_plan")

    def __init__(self, config: PlannerConfig, quantiles: ChanceQuantiles) -> None:
        if self.critics not in TASK_KINDS:
            raise ValueError(f"task kind {type(self).__name__}: critics {self.critics!r} must be one of the kernels' "
                             f"task kinds {list(TASK_KINDS)}")
        self.config = config
        self.quantiles = quantiles
        self.cost: CostBundle = config.cost_bundle(self.critics)  # the critic chain as the kernels read it
        self.noise_std = np.array(config.noise_std, dtype=np.float64)  # the sampling noise of its rollouts

    def reset(self) -> None:  # noqa: B027 - a hook: a kind with nothing to forget keeps it
        """Forget what depends on where the planner started planning (plans repeat from here)."""

    def prepare(self, task: object, x: np.ndarray) -> None:  # noqa: B027 - a hook: nothing to build ahead
        """Build now what this kind caches per task for plans from state `x` (`Planner.prepare_task`)."""

    def check(self, task: object) -> None:  # noqa: B027 - a hook: a kind with no checks of its own keeps it
        """Raise a ValueError if the planner cannot plan for `task` (the task's own checks are its type's)."""

    @abstractmethod
    def bounds(self, task: object, states: np.ndarray, covs: np.ndarray) -> tuple[np.ndarray, int]:
        """The chance-constrained bounds (N+1, ...) along `states` with covariances `covs`, and the clamp count."""

    @abstractmethod
    def task_bundle(self, task: object, bounds: np.ndarray, x: np.ndarray) -> TaskBundle:
        """The kernels' task input for `task` with `bounds`, planning from state `x`."""

    @classmethod
    def per_step(cls, task: object, bounds: np.ndarray) -> np.ndarray:
        """One number a step (N+1,) [m] of `bounds` (`bounds`' result) for a plan message (`Plan.tightened`): here the
        bounds themselves (a lane's tightened half-widths)."""
        return np.asarray(bounds, dtype=np.float64).reshape(-1)

    def speed_limit(self, task: object, x: np.ndarray) -> float | None:
        """A bound [m/s] on the commanded speed of this task's plans from state `x` (None: the planner's
        `v_limits` only)."""
        return None

    def reach(self) -> float:
        """How far [m] one horizon can drive at the largest speed."""
        c = self.config
        return c.horizon * c.dt * max(abs(c.v_limits[0]), abs(c.v_limits[1]))


_KINDS: dict[type, type[TaskKind]] = {}


def register(kind: type[TaskKind]) -> type[TaskKind]:
    """Make `kind` the kind of its `task_type`'s tasks (a class decorator); another kind of that type is replaced."""
    if kind.critics not in TASK_KINDS:
        raise ValueError(f"task kind {kind.__name__}: critics {kind.critics!r} must be one of the kernels' task kinds "
                         f"{list(TASK_KINDS)}")
    _KINDS[kind.task_type] = kind
    return kind


def registered_kinds() -> dict[type, type[TaskKind]]:
    """The registered kinds by task type."""
    return dict(_KINDS)


def kind_class_for(task: object) -> type[TaskKind]:
    """The kind of `task`'s type, or a ValueError that names the task types there are kinds for."""
    kind = _KINDS.get(type(task))
    if kind is None:
        names = " or ".join(t.__name__ for t in _KINDS)
        raise ValueError(f"task must be a {names}, got {type(task).__name__}: no task kind plans for it "
                         "(register one with gpmppi.mppi.task_kinds.register)")
    return kind


@register
class LaneKind(TaskKind):
    """Follow a lane: the half-width tightened by the covariance, the lane critics, the lane noise."""

    task_type = LaneTask
    critics = "lane"
    clamp_flag = "half_width_clamped_steps"

    def __init__(self, config: PlannerConfig, quantiles: ChanceQuantiles) -> None:
        super().__init__(config, quantiles)
        std = config.noise_std if config.lane_noise_std is None else config.lane_noise_std
        self.noise_std = np.array(std, dtype=np.float64)
        self._lane_key: tuple | None = None
        self._lane: LaneLookup | None = None

    def bounds(self, task: LaneTask, states: np.ndarray, covs: np.ndarray) -> tuple[np.ndarray, int]:
        """Tightened half-widths (N+1,)."""
        c = self.config
        return tighten_lane(covs, float(task.half_width), self.quantiles.chi2_2, c.min_half_width_fraction)

    def task_bundle(self, task: LaneTask, bounds: np.ndarray, x: np.ndarray) -> TaskBundle:
        return TaskBundle.for_lane(self.lane_lookup(task), float(task.half_width), bounds, float(task.speed_target))

    def lane_lookup(self, task: LaneTask) -> LaneLookup:
        """The lane's lookup grid (built once per lane)."""
        key = (task.centerline.shape, hash(task.centerline.tobytes()), task.closed)
        if key != self._lane_key:
            c = self.config
            margin = task.half_width + min(self.reach(), 10.0) + 1.0
            self._lane = cached_lane_lookup(task.centerline, task.closed, margin, c.lane_cell)
            self._lane_key = key
        assert self._lane is not None
        return self._lane


@register
class GoalKind(TaskKind):
    """Reach a goal among circles and an occupancy grid's lethal cells: the circles, and the grid's radius, inflated by
    the covariance; the goal critics."""

    task_type = GoalTask
    critics = "goal"
    clamp_flag = "inflation_capped"

    def reset(self) -> None:
        # the scene whose goal field this planner uses, and the position it first planned that scene from
        self._goal_scene: bytes | None = None
        self._goal_extent = np.zeros((1, 2))
        self._goal_checked: tuple | None = None  # the (grid, goal) whose goal was found clear of the grid

    def __init__(self, config: PlannerConfig, quantiles: ChanceQuantiles) -> None:
        super().__init__(config, quantiles)
        self.reset()

    def check(self, task: GoalTask) -> None:
        o = task.obstacles
        if o.shape[0]:
            d = np.hypot(o[:, 0] - task.goal[0], o[:, 1] - task.goal[1])
            inside = np.nonzero(d < o[:, 2] + self.config.robot_radius)[0]
            if inside.size:
                raise ValueError(
                    f"task.goal {task.goal.tolist()} lies inside obstacle {int(inside[0])} "
                    f"{o[inside[0]].tolist()}; move the goal out of the obstacles"
                )
        grid = task.costmap
        key = None if grid is None else (grid.digest(), task.goal.tobytes())
        if grid is not None and key != self._goal_checked:  # once per goal and grid: off the plans' path
            clear = float(grid.clearance(task.goal[None, :], self.config.robot_radius)[0])
            if clear < 0.0:
                raise ValueError(f"task.goal {task.goal.tolist()} lies within {-clear:.2f} m of the costmap's lethal "
                                 "cells (robot radius included); move the goal into free space")
            self._goal_checked = key

    def bounds(self, task: GoalTask, states: np.ndarray, covs: np.ndarray) -> tuple[np.ndarray, int]:
        """Effective obstacle radii (N+1, K), and with a costmap a last column: the distance from a lethal cell's
        centre the rollouts must keep (`costmap.lethal_radius` inflated by the covariance, `costs.inflate_grid`)."""
        c = self.config
        radii, capped = inflate_obstacles(states, covs, task.obstacles, self.quantiles.normal, c.robot_radius,
                                          c.max_inflation)
        if task.costmap is not None:
            grid_r, grid_capped = inflate_grid(covs, self.quantiles.normal,
                                               lethal_radius(c.robot_radius, task.costmap.resolution), c.max_inflation)
            radii = np.concatenate([radii, grid_r[:, None]], axis=1)
            capped += grid_capped
        if c.step_clearance:
            half_step = 0.5 * c.dt * max(abs(c.v_limits[0]), abs(c.v_limits[1]))
            radii = np.sqrt(radii * radii + half_step * half_step)
        return radii, capped

    @classmethod
    def per_step(cls, task: GoalTask, bounds: np.ndarray) -> np.ndarray:
        """Per step the largest inflation of any radius (a costmap's column, after the circles', is its whole radius:
        the robot's plus the inflation); zeros with nothing to inflate."""
        bounds = np.asarray(bounds, dtype=np.float64)
        radii = np.concatenate([task.obstacles[:, 2], np.zeros(bounds.shape[1] - task.obstacles.shape[0])])
        return (bounds - radii[None, :]).max(axis=1) if radii.size else np.zeros(bounds.shape[0])

    def speed_limit(self, task: GoalTask, x: np.ndarray) -> float | None:
        """The task's approach bound where `x` is (`GoalTask.speed_bound`; the caution on unknown ground sets it)."""
        return task.speed_bound(x[:2])

    def prepare(self, task: GoalTask, x: np.ndarray) -> None:
        """A grid's kernel arrays (its distance transform) and the goal field of the task's scene."""
        if task.costmap is not None:
            task.costmap.kernel_arrays()
        self.goal_field(task, x)

    def task_bundle(self, task: GoalTask, bounds: np.ndarray, x: np.ndarray) -> TaskBundle:
        return TaskBundle.for_goal(task.goal, task.obstacles, bounds, self.goal_field(task, x), task.costmap)

    def goal_field(self, task: GoalTask, x: np.ndarray) -> GoalField | None:
        """The geodesic goal field of the task's scene (built once per scene; None for straight-line distance).

        Circles are the obstacles grown by the robot radius; the grid covers the scene and the robot's
        position when this planner first planned the scene (since its last `reset`), plus the distance a horizon
        can drive. That position is part of the shared cache's key: a field another planner of the process built
        from elsewhere covers another grid, and its interpolated distances (so the plans) differ in the last bits.
        """
        c = self.config
        if c.goal_distance != "geodesic":
            return None
        circles = task.obstacles.copy()
        circles[:, 2] += c.robot_radius
        scene = task.goal.tobytes() + circles.tobytes() + (b"" if task.costmap is None else task.costmap.digest())
        if scene != self._goal_scene:
            self._goal_scene, self._goal_extent = scene, x[None, :2].copy()
        return cached_goal_field(task.goal, circles, self._goal_extent, margin=min(self.reach(), 10.0),
                                 cell=c.goal_cell, costmap=task.costmap, clearance=c.robot_radius)
