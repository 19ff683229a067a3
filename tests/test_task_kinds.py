"""Task kinds are plug-ins: a kind defined here (a waypoint: a goal with no obstacles) plans through the planner's
own iteration, scored by the goal critics it names, and a task of no registered kind is refused by name."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
from cached_models import shipped_model

from gpmppi.evaluation import task_runs
from gpmppi.evaluation.closed_loop import ClosedLoopConfig, run_closed_loop
from gpmppi.evaluation.task_runs import TaskRun, run_for
from gpmppi.mppi import task_kinds
from gpmppi.mppi.bundles import TaskBundle
from gpmppi.mppi.caution import CautionConfig, cautious_task
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.mppi.task_kinds import TaskKind
from gpmppi.scenarios import Scenario, infeasibility
from gpmppi.tasks import GoalTask, TaskOutline

W = np.array([0.5, 0.3, 0.2])


@dataclass(frozen=True)
class WaypointTask:
    """Drive to a point; nothing to avoid. Its plain part (`gpmppi.tasks`): what the views draw, why a run cannot
    start, the task while the ground is unknown, the task in a world with a grid."""

    point: np.ndarray
    kind: ClassVar[str] = "waypoint"

    def outline(self) -> TaskOutline:
        return TaskOutline(f"waypoint {self.point.tolist()}", goal=self.point, tolerance=0.5)

    def start_problems(self, start: np.ndarray, robot_radius: float) -> list[str]:
        return ["start is the waypoint"] if np.allclose(start[:2], self.point) else []

    def cautious(self, speed_scale: float, approach: tuple[float, float] | None = None) -> WaypointTask:
        return self

    def with_costmap(self, costmap: object, replace_own: bool = False) -> WaypointTask:
        return self


class WaypointKind(TaskKind):
    task_type = WaypointTask
    critics = "goal"
    clamp_flag = "waypoint_clamped"

    def check(self, task: WaypointTask) -> None:
        if not np.all(np.isfinite(task.point)):
            raise ValueError("waypoint must be finite")

    def bounds(self, task: WaypointTask, states: np.ndarray, covs: np.ndarray) -> tuple[np.ndarray, int]:
        return np.zeros((states.shape[0], 0)), 0  # no circles to inflate

    def task_bundle(self, task: WaypointTask, bounds: np.ndarray, x: np.ndarray) -> TaskBundle:
        return TaskBundle.for_goal(np.asarray(task.point, dtype=np.float64), np.zeros((0, 3)), bounds, None)


class WaypointRun(TaskRun):
    """The evaluation of a waypoint: stop within 0.5 m of it, scored by whether it got there."""

    task_type = WaypointTask

    def limits(self, lane_distance_m: float, goal_time_limit_s: float) -> dict:
        return {"time_limit_s": goal_time_limit_s}

    def stop(self, true_state: np.ndarray, driven_m: float, cfg: ClosedLoopConfig) -> str | None:
        return "goal" if np.linalg.norm(true_state[:2] - self.task.point) <= 0.5 else None

    def score(self, positions: np.ndarray, times: np.ndarray, status: str, cfg: ClosedLoopConfig) -> dict:
        return {"success": status == "goal"}


@pytest.fixture
def waypoint_kind(monkeypatch):  # noqa: ANN001, ANN201
    """WaypointKind (and its evaluation, WaypointRun) registered for this test only."""
    monkeypatch.setattr(task_kinds, "_KINDS", dict(task_kinds._KINDS))
    monkeypatch.setattr(task_runs, "_RUNS", dict(task_runs._RUNS))
    task_kinds.register(WaypointKind)
    task_runs.register(WaypointRun)
    return WaypointKind


@pytest.fixture(scope="module")
def model():  # noqa: ANN201
    return shipped_model()


def test_a_new_task_kind_plugs_in(model, waypoint_kind) -> None:  # noqa: ANN001
    """The toy kind plans as a goal task with the same point and no obstacles does (the same critics and inputs),
    bit for bit, and reports its own clamp flag."""
    cfg = PlannerConfig(backend="cpu", samples=64, seed=3, goal_distance="euclidean", step_clearance=False)
    mine, ref = Planner(cfg, model), Planner(cfg, model)
    point = np.array([4.0, 3.0])
    x_mine = x_ref = np.array([0.0, 0.0, 0.5, 0.0, 0.0])
    for _ in range(3):
        a = mine.plan(x_mine, WaypointTask(point), W)
        b = ref.plan(x_ref, GoalTask(goal=point), W)
        np.testing.assert_array_equal(a.controls, b.controls)
        assert a.cost == b.cost and a.critic_costs == b.critic_costs
        assert a.flags["waypoint_clamped"] == 0 and "inflation_capped" not in a.flags
        x_mine, x_ref = a.states[1].copy(), b.states[1].copy()
    assert isinstance(mine.kind(WaypointTask(point)), WaypointKind)
    with pytest.raises(ValueError, match="waypoint must be finite"):
        mine.plan(x_mine, WaypointTask(np.array([np.nan, 0.0])), W)


def test_a_new_task_kind_drives_a_closed_loop(model, waypoint_kind) -> None:  # noqa: ANN001
    """The evaluation's closed loop drives the toy kind to its point and stops there by the kind's own rule."""
    from gpmppi.evaluation.runner import EvalSettings, make_plant

    settings = EvalSettings(samples=128)
    planner = Planner(PlannerConfig(backend="cpu", samples=128, seed=1, goal_distance="euclidean"), model)
    task = WaypointTask(np.array([2.5, 1.5]))
    limits = run_for(task).limits(settings.lane_distance_m, 12.0)
    traj = run_closed_loop(planner, make_plant(settings, model.terrains[0], 0), task, np.zeros(5),
                           len(model.terrains), ClosedLoopConfig(**limits, adapt_weights=False))
    assert traj.status == "goal", traj.message
    assert np.linalg.norm(traj.positions[-1] - task.point) <= 0.5
    assert run_for(task).score(traj.positions, traj.times, traj.status, None) == {"success": True}


def test_what_outside_the_kinds_handles_a_task_needs_no_change_for_a_new_kind() -> None:
    """The code that once branched on lane or goal asks the kind: the views draw the toy's outline (its goal circle,
    no lane, no circles; its plan bounds as inflation), a scenario asks it why it cannot start, the caution and the
    planner's per-step bounds take it as it is."""
    from gpmppi.mppi.task_kinds import kind_class_for
    from schemas import Plan
    from services.view import geometry as geo

    task = WaypointTask(np.array([4.0, 3.0]))
    lines = geo.task_lines(task.outline())
    assert list(lines) == ["goal"] and lines["goal"][0] == "goal"
    np.testing.assert_allclose(np.hypot(*(lines["goal"][1][0] - task.point).T), 0.5)
    plan = Plan.model_construct(tightened=[0.1, 0.2])
    assert geo.plan_bounds(plan, np.zeros((2, 5)), task.outline()) == ("inflated", [])  # no circles to grow
    assert WaypointKind.per_step(task, np.zeros((41, 0))).shape == (0,)  # the plan message's bounds: none
    assert infeasibility(Scenario("toy", task, np.array([4.0, 3.0, 0.0, 0.0, 0.0]))) == ["start is the waypoint"]
    assert infeasibility(Scenario("toy", task, np.zeros(5))) == []
    assert cautious_task(task, CautionConfig()) is task
    with pytest.raises(ValueError, match="no task kind plans for it"):
        kind_class_for(task)  # registered only by the fixture below


def test_a_task_of_no_kind_is_refused_not_scored_as_a_goal(model) -> None:  # noqa: ANN001
    p = Planner(PlannerConfig(backend="cpu", samples=16), model)
    with pytest.raises(ValueError, match=r"task must be a LaneTask or GoalTask, got WaypointTask"):
        p.plan(np.zeros(5), WaypointTask(np.ones(2)), W)
    with pytest.raises(ValueError, match="the evaluation runs a LaneTask or GoalTask, got WaypointTask"):
        run_for(WaypointTask(np.ones(2)))


def test_the_kernels_refuse_a_task_kind_they_have_no_critics_for() -> None:
    bundle = TaskBundle.for_goal(np.ones(2), np.zeros((0, 3)), np.zeros((3, 0)), None)
    bundle.args()
    object.__setattr__(bundle, "kind", 2)
    with pytest.raises(ValueError, match="TaskBundle.kind must be one of the kernels' task kinds"):
        bundle.args()


def test_a_kind_must_name_a_critic_chain_of_the_kernels() -> None:
    class Nowhere(WaypointKind):
        critics = "nowhere"

    with pytest.raises(ValueError, match="critics 'nowhere' must be one of the kernels' task kinds"):
        task_kinds.register(Nowhere)
