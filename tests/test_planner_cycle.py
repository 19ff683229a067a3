"""The planning cycle (`PlannerCycle`), free of Zenoh: every refusal by name, weight updates and their ages, the
start covariance, delay compensation; and that the closed-loop evaluation runs exactly this cycle."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from gpmppi.mppi.cycle import Event, Planned, PlannerCycle
from gpmppi.mppi.cycle_config import CycleConfig
from gpmppi.tasks import GoalTask, LaneTask

NS = 1_000_000_000
LANE = LaneTask(np.array([[0.0, 0.0], [100.0, 0.0]]), half_width=1.0, closed=False)
X0 = np.array([1.0, 0.0, 0.0, 1.0, 0.0])


@dataclass
class Result:
    control: np.ndarray
    states: np.ndarray


class RecordingPlanner:
    """Records every call; `fail` makes plan raise, `nan` makes it return a non-finite trajectory."""

    def __init__(self) -> None:
        self.calls: list[dict] = []
        self.prepared: list[np.ndarray] = []
        self.resets = 0
        self.fail: Exception | None = None
        self.nan = False
        self.refuse_weights = False

    def plan(self, state, task, weights=None, state_cov=None, delay_s=0.0) -> Result:
        self.calls.append({"state": state.copy(), "weights": np.array(weights), "cov": state_cov, "delay": delay_s})
        if self.fail is not None:
            raise self.fail
        states = np.full((3, 5), np.nan if self.nan else 0.0)
        return Result(np.array([1.0, 0.0]), states)

    def prepare(self, weights) -> None:
        if self.refuse_weights:
            raise ValueError("weights must lie on the simplex")
        self.prepared.append(np.array(weights))

    def reset(self) -> None:
        self.resets += 1


def make(config: CycleConfig | None = None, task=LANE, clock=lambda: 0.0) -> tuple[PlannerCycle, RecordingPlanner]:
    planner = RecordingPlanner()
    return PlannerCycle(planner, task, config or CycleConfig(), 2, ["asphalt", "grass"], clock=clock), planner


def refusal(out: Planned | Event) -> str:
    assert isinstance(out, Event), out
    return out.name


def test_each_refusal_is_named_counted_and_gives_no_plan() -> None:
    cycle, planner = make(CycleConfig(max_state_age_s=0.5, max_state_future_s=0.2))
    now_ns = 100 * NS
    assert refusal(cycle.on_state(X0, now_ns - NS, 0.0, now_ns)) == "state_stale"
    out = cycle.on_state(X0, now_ns + NS // 2, 0.0, now_ns)
    assert refusal(out) == "state_future" and "future" in out.message
    assert refusal(cycle.on_state([1.0, np.nan, 0.0, 0.0, 0.0], now_ns, 0.0, now_ns)) == "state_nonfinite"
    assert refusal(cycle.on_state([1.0, 2.0], now_ns, 0.0, now_ns)) == "state_nonfinite"
    assert not planner.calls  # none of these reached the planner
    # inside both limits: planned
    assert isinstance(cycle.on_state(X0, now_ns - NS // 4, 0.0, now_ns), Planned)
    assert isinstance(cycle.on_state(X0, now_ns + NS // 10, 0.0, now_ns), Planned)
    planner.fail = ValueError("delay_s must be between 0 and the horizon")
    out = cycle.on_state(X0, now_ns, 0.0, now_ns)
    assert refusal(out) == "plan_failed" and out.level == "error" and "delay_s" in out.message
    planner.fail, planner.nan = None, True
    assert refusal(cycle.on_state(X0, now_ns, 0.0, now_ns)) == "plan_nonfinite"
    no_task, _ = make(task=None)
    assert refusal(no_task.on_state(X0, now_ns, 0.0, now_ns)) == "no_task"
    assert cycle.counts == {"state_stale": 1, "state_future": 1, "state_nonfinite": 2, "plan_failed": 1,
                            "plan_nonfinite": 1}
    assert [e.name for e in cycle.drain_events()][:3] == ["state_stale", "state_future", "state_nonfinite"]
    assert cycle.drain_events() == []


def test_a_task_of_another_kind_and_an_odometry_jump_reset_the_warm_start() -> None:
    cycle, planner = make()
    assert isinstance(cycle.on_state(X0, NS, 0.0, NS), Planned)
    step = X0 + np.array([0.1, 0.0, 0.0, 0.0, 0.0])
    assert isinstance(cycle.on_state(step, NS + NS // 10, 0.1, NS + NS // 10), Planned)
    assert planner.resets == 0
    jumped = X0 + np.array([5.0, 0.0, 0.0, 0.0, 0.0])
    assert isinstance(cycle.on_state(jumped, NS + NS // 5, 0.2, NS + NS // 5), Planned)  # still plans, from scratch
    assert planner.resets == 1 and cycle.counts["odom_jump"] == 1
    # a replanned path (a lane for a lane) keeps the warm start: the robot drives on through the swap
    other = LaneTask(np.array([[0.0, 0.0], [0.0, 50.0]]), half_width=1.0, closed=False)
    cycle.set_task(other)
    assert planner.resets == 1 and cycle.task is other
    goal = GoalTask(goal=np.array([10.0, 0.0]))
    cycle.set_task(goal)
    assert planner.resets == 2 and cycle.task is goal
    cycle.set_task(GoalTask(goal=np.array([12.0, 1.0])))  # a moved goal keeps it too
    assert planner.resets == 2


def test_start_covariance_from_the_state_or_the_configured_one() -> None:
    cycle, planner = make()
    cov = np.diag([0.01, 0.01, 0.001, 0.02, 0.02])
    cycle.on_state(X0, NS, 0.0, NS, covariance=cov.reshape(-1).tolist())  # flat, as the State message has it
    np.testing.assert_array_equal(planner.calls[-1]["cov"], cov)
    bad = cov.copy()
    bad[0, 0] = -1.0
    assert isinstance(cycle.on_state(X0, NS, 0.0, NS, covariance=bad), Planned)
    assert planner.calls[-1]["cov"] is None and cycle.counts["state_covariance_invalid"] == 1
    asymmetric = cov.copy()
    asymmetric[0, 1] = 0.5
    cycle.on_state(X0, NS, 0.0, NS, covariance=asymmetric)
    assert planner.calls[-1]["cov"] is None and cycle.counts["state_covariance_invalid"] == 2
    cycle.on_state(X0, NS, 0.0, NS)
    assert planner.calls[-1]["cov"] is None and cycle.counts["state_covariance_invalid"] == 2


def test_delay_is_state_age_plus_last_compute_plus_actuation() -> None:
    clock = iter([10.0, 10.03, 20.0, 20.05])
    cycle, planner = make(CycleConfig(actuation_delay_s=0.005), clock=lambda: next(clock))
    first = cycle.on_state(X0, NS, 0.0, NS + NS // 10)  # 0.1 s old, no plan timed yet
    assert isinstance(first, Planned) and first.delay_s == pytest.approx(0.105)
    assert first.plan_s == pytest.approx(0.03)
    second = cycle.on_state(X0, 2 * NS, 0.0, 2 * NS - NS // 10)  # stamped 0.1 s ahead: counts as age 0
    assert isinstance(second, Planned) and second.delay_s == pytest.approx(0.03 + 0.005)
    assert [c["delay"] for c in planner.calls] == [first.delay_s, second.delay_s]
    off, planner = make(CycleConfig(compensate_delay=False, actuation_delay_s=0.005))
    off.on_state(X0, NS, 0.0, NS + NS // 10)
    assert planner.calls[-1]["delay"] == 0.0


def test_weights_by_name_prepared_on_arrival_refused_when_wrong() -> None:
    cycle, planner = make()
    np.testing.assert_array_equal(cycle.weights, [0.5, 0.5])  # the prior until the terrain service speaks
    assert cycle.on_weights([0.2, 0.8], 1.0, names=["grass", "asphalt"])
    np.testing.assert_array_equal(cycle.weights, [0.8, 0.2])  # the model's order
    np.testing.assert_array_equal(planner.prepared[-1], [0.8, 0.2])  # collapsed now, not on the state's path
    assert not cycle.on_weights([0.5, 0.5], 1.1, names=["asphalt", "ice"])
    planner.refuse_weights = True
    assert not cycle.on_weights([2.0, -1.0], 1.2)
    assert cycle.counts == {"weights_invalid": 2}
    np.testing.assert_array_equal(cycle.weights, [0.8, 0.2])  # kept
    cycle.on_state(X0, NS, 1.3, NS)
    np.testing.assert_array_equal(planner.calls[-1]["weights"], [0.8, 0.2])


def test_weights_naming_a_ground_learned_after_the_model_wait_for_it_and_age_as_usual() -> None:
    """Weights that name the model's grounds and a learned one (they may reach the planner before the `ModelUpdate`
    that brings its model) are not refused: counted, the previous weights kept, which age as any others do."""
    cycle, planner = make(CycleConfig(weights_stale_after_s=1.0, weights_fallback_after_s=3.0))
    assert cycle.on_weights([0.2, 0.8], 0.0, names=["grass", "asphalt"])
    assert not cycle.on_weights([0.1, 0.1, 0.8], 0.5, names=["asphalt", "grass", "new-1"])
    assert cycle.counts == {"weights_ahead_of_model": 1}  # not weights_invalid
    assert not [e for e in cycle.drain_events() if e.level != "count"]  # nothing logged
    np.testing.assert_array_equal(cycle.weights, [0.8, 0.2])
    out = cycle.on_state(X0, NS, 1.5, NS)
    assert isinstance(out, Planned) and out.weights_stale  # not refreshed by weights the model cannot take
    assert not cycle.on_weights([0.5, 0.5], 1.6, names=["asphalt", "ice"])  # a ground missing: still refused
    assert cycle.counts["weights_invalid"] == 1


def test_silent_weights_are_flagged_stale_then_replaced_by_the_prior() -> None:
    cycle, planner = make(CycleConfig(weights_stale_after_s=1.0, weights_fallback_after_s=3.0))
    cycle.on_weights([0.9, 0.1], 0.0)
    out = cycle.on_state(X0, NS, 0.5, NS)
    assert isinstance(out, Planned) and not out.weights_stale and not cycle.weights_prior
    out = cycle.on_state(X0, NS, 1.5, NS)
    assert isinstance(out, Planned) and out.weights_stale and cycle.counts["weights_stale"] == 1
    np.testing.assert_array_equal(planner.calls[-1]["weights"], [0.9, 0.1])  # kept while stale
    cycle.tick(2.0)
    assert cycle.counts["weights_stale"] == 1  # once per silence
    out = cycle.on_state(X0, NS, 3.5, NS)
    assert isinstance(out, Planned) and out.weights_stale and cycle.weights_prior
    np.testing.assert_array_equal(planner.calls[-1]["weights"], [0.5, 0.5])
    np.testing.assert_array_equal(planner.prepared[-1], [0.5, 0.5])
    assert cycle.counts["weights_fallback"] == 1
    cycle.on_weights([0.9, 0.1], 4.0)
    assert not cycle.weights_stale and cycle.counts["weights_back"] == 1
    # the prior itself never goes stale: falling back would change nothing
    quiet, _ = make(CycleConfig(weights_stale_after_s=1.0, weights_fallback_after_s=3.0))
    quiet.on_weights([0.5, 0.5], 0.0)
    quiet.tick(10.0)
    assert not quiet.weights_stale and "weights_stale" not in quiet.counts


def test_the_closed_loop_runs_this_cycle() -> None:
    """A seeded closed loop (physics plant, terrain estimator, command latency) and the same cycle driven by hand
    from its measured states give identical commands and weights, bit for bit."""
    from cached_models import shipped_model

    from gpmppi.evaluation.closed_loop import ClosedLoopConfig, run_closed_loop
    from gpmppi.mppi.planner import Planner, PlannerConfig
    from gpmppi.plant.physics import PhysicsPlant
    from gpmppi.plant.terrains import load_terrains
    from gpmppi.scenarios import circle_lane
    from gpmppi.terrain.least_squares import TerrainEstimator

    model = shipped_model()
    sc = circle_lane()
    from gpmppi.terrain.cycle import TerrainCycleConfig

    # pairing by stamp: each transition with the command planned from its first state, as the loop below does
    cfg = ClosedLoopConfig(time_limit_s=1.5, latency_s=0.1, terrain=TerrainCycleConfig(pairing="stamp"))
    traj = run_closed_loop(Planner(PlannerConfig(samples=64, seed=3), model),
                           PhysicsPlant(load_terrains(None), "grass", seed=3), sc.task, sc.start,
                           len(model.terrains), cfg, estimator=TerrainEstimator(model))
    assert traj.status == "time_limit" and len(traj.commands) == 15

    planner = Planner(PlannerConfig(samples=64, seed=3), model)
    cycle = PlannerCycle(planner, sc.task, CycleConfig(actuation_delay_s=0.1), len(model.terrains),
                         clock=lambda: 0.0)
    estimator = TerrainEstimator(model)
    commands, weights = [], []
    for k, x in enumerate(traj.measured_states[:-1]):
        stamp = round(k * 0.1 * NS)
        # as the terrain service: state k-1's solve waits for its command (at the base 0.1 s late, after state k
        # arrived: so command_wait_s, 0.05 s) and observes the transition k-2 -> k-1; the plan for k gets it
        if k > 0:
            if k > 1:
                estimator.observe(traj.measured_states[k - 2], commands[k - 2], traj.measured_states[k - 1])
            w = np.clip(np.asarray(estimator.estimate().weights, dtype=np.float64), 0.0, 1.0)
            cycle.on_weights(w / w.sum(), (k - 1) * 0.1 + 0.05)  # clean-up: on the simplex, as it publishes them
        out = cycle.on_state(x, stamp, k * 0.1, stamp)
        assert isinstance(out, Planned) and out.delay_s == 0.1
        commands.append(np.asarray(out.result.control).copy())
        weights.append(cycle.weights.copy())
    np.testing.assert_array_equal(np.array(commands), traj.commands)
    np.testing.assert_array_equal(np.array(weights), traj.weights)
    assert not np.allclose(traj.weights[-1], traj.weights[0])  # the estimator moved them: the weight path ran


class ResumingPlanner(RecordingPlanner):
    """Records `resume` calls (a planner taking over from a predecessor's plan)."""

    def __init__(self) -> None:
        super().__init__()
        self.resumed: list[tuple[np.ndarray, int]] = []

    def resume(self, controls, steps) -> bool:
        if steps >= len(controls):
            return False
        self.resumed.append((np.array(controls), steps))
        return True


def test_a_takeover_resumes_from_the_predecessors_plan_shifted_to_the_first_state() -> None:
    planner = ResumingPlanner()
    cycle = PlannerCycle(planner, LANE, CycleConfig(), 2, ["asphalt", "grass"], clock=lambda: 0.0)
    controls = np.column_stack([np.linspace(1.0, 1.4, 5), np.zeros(5)])
    plan_ns = 100 * NS
    cycle.resume_from(controls, plan_ns, dt=0.1)
    # the first state is 0.31 s after the predecessor's plan's state: three steps of its sequence have gone by
    now_ns = plan_ns + int(0.31 * NS)
    assert isinstance(cycle.on_state(X0, now_ns, 0.0, now_ns), Planned)
    assert len(planner.resumed) == 1 and planner.resumed[0][1] == 3
    assert np.array_equal(planner.resumed[0][0], controls)
    assert [e.name for e in cycle.drain_events()] == ["resumed"]
    # once only: the next state plans from the planner's own warm start
    assert isinstance(cycle.on_state(X0, now_ns + NS // 10, 0.0, now_ns + NS // 10), Planned)
    assert len(planner.resumed) == 1


def test_a_plan_older_than_its_horizon_is_not_resumed_from() -> None:
    planner = ResumingPlanner()
    cycle = PlannerCycle(planner, LANE, CycleConfig(), 2, ["asphalt", "grass"], clock=lambda: 0.0)
    cycle.resume_from(np.ones((5, 2)), 100 * NS, dt=0.1)
    now_ns = 100 * NS + NS  # 10 steps later: the 5-step sequence has run out
    assert isinstance(cycle.on_state(X0, now_ns, 0.0, now_ns), Planned)
    assert not planner.resumed and [e.name for e in cycle.drain_events()] == ["resume_skipped"]


def _wall() -> object:
    from gpmppi.costmap import Costmap

    values = np.zeros((80, 80), dtype=np.int16)
    values[:, 40:44] = 100  # a wall across the grid at x 2.0-2.2 m (5 cm cells)
    return Costmap(values, 0.05, (0.0, 0.0, 0.0))


def test_a_goal_in_a_lethal_cell_is_refused_by_name_and_the_last_task_kept() -> None:
    goal_task = GoalTask(goal=np.array([3.5, 1.0]))
    cycle, planner = make(task=goal_task)
    cycle.set_costmap(_wall(), now=0.0)
    before = cycle.task
    cycle.set_task(GoalTask(goal=np.array([2.1, 1.0])))  # inside the wall
    assert [e.name for e in cycle.drain_events()] == ["goal_lethal"]
    assert cycle.task is before and cycle.counts["goal_lethal"] == 1
    cycle.set_task(GoalTask(goal=np.array([1.0, 3.0])))  # free space: taken
    assert not cycle.drain_events() and np.allclose(cycle.task.goal, [1.0, 3.0])


def test_a_sensor_grid_too_old_stops_planning_until_a_new_one_arrives() -> None:
    now = [0.0]
    cycle, planner = make(CycleConfig(max_costmap_age_s=1.0, compensate_delay=False),
                          task=GoalTask(goal=np.array([1.0, 3.0])), clock=lambda: now[0])
    cycle.set_costmap(_wall(), now=10.0)
    stamp = 5 * NS
    assert isinstance(cycle.on_state(X0, stamp, 10.5, stamp), Planned)
    assert refusal(cycle.on_state(X0, stamp + NS // 10, 11.2, stamp + NS // 10)) == "costmap_stale"
    assert len(planner.calls) == 1  # no plan among the stale grid: no command, egress's watchdog stops the robot
    cycle.set_costmap(_wall(), now=11.3)  # a fresh grid: planning again
    assert isinstance(cycle.on_state(X0, stamp + NS // 5, 11.4, stamp + NS // 5), Planned)
    # a grid that came with the task (a scene file's map) never ages
    cycle.set_costmap(None, now=11.4)
    cycle.set_task(GoalTask(goal=np.array([1.0, 3.0]), costmap=_wall()))
    assert isinstance(cycle.on_state(X0, stamp + 3 * NS, 100.0, stamp + 3 * NS), Planned)


class WarmStartSpy:
    """A real `Planner` whose warm start is read just before each plan (the sequence that plan starts from)."""

    def __init__(self, planner) -> None:
        self.planner = planner
        self.starts: list[np.ndarray] = []

    def __getattr__(self, name: str):
        return getattr(self.planner, name)

    def plan(self, *args, **kwargs):
        self.starts.append(self.planner._nominal.copy())
        return self.planner.plan(*args, **kwargs)


def test_the_warm_start_follows_the_states_stamps_across_a_lost_state() -> None:
    """States lost between two plans (an ingress that took over, a state dropped under load): the next plan starts
    from the last plan's sequence shifted by the steps its stamps say have gone by, not by one step per plan, so it
    is not a step behind the robot; a state one dt later (with jitter) shifts one step, as always."""
    from cached_models import shipped_model

    from gpmppi.mppi.planner import Planner, PlannerConfig

    model = shipped_model()
    planner = Planner(PlannerConfig(samples=32, horizon=8, seed=5), model)
    spy = WarmStartSpy(planner)
    cycle = PlannerCycle(spy, LANE, CycleConfig(compensate_delay=False), len(model.terrains), clock=lambda: 0.0)
    t0 = 100 * NS
    x = X0.copy()
    results = []
    # a state every 0.1 s (one 14 ms late), then two lost: the next comes 0.3 s after the last planned from
    for stamp in (t0, t0 + NS // 10 + 14_000_000, t0 + 2 * NS // 10, t0 + 5 * NS // 10):
        out = cycle.on_state(x, stamp, 0.0, stamp)
        assert isinstance(out, Planned)
        results.append(out.result.controls.copy())

    def shifted(u: np.ndarray, steps: int) -> np.ndarray:
        return np.concatenate([u[steps:], np.repeat(u[-1:], steps, axis=0)], axis=0)

    np.testing.assert_array_equal(spy.starts[1], shifted(results[0], 1))
    np.testing.assert_array_equal(spy.starts[2], shifted(results[1], 1))
    # without the stamps this would be shifted(results[2], 1): the command for 0.2 s ago applied now
    np.testing.assert_array_equal(spy.starts[3], shifted(results[2], 3))
    assert not np.array_equal(spy.starts[3], shifted(results[2], 1))
    assert cycle.counts.get("warm_start_caught_up") == 1
    assert [e.level for e in cycle.drain_events() if e.name == "warm_start_caught_up"] == ["count"]


def test_catch_up_drops_the_steps_gone_by_beyond_one() -> None:
    from cached_models import shipped_model

    from gpmppi.mppi.planner import Planner, PlannerConfig

    planner = Planner(PlannerConfig(samples=32, horizon=6, seed=5), shipped_model())
    u = np.column_stack([np.linspace(0.5, 1.0, 6), np.linspace(-0.5, 0.0, 6)])
    planner._nominal = u.copy()
    for elapsed in (0.0, 0.05, 0.1, 0.149, float("nan")):  # one dt or less (or unknown): the plan's own shift only
        assert planner.catch_up(elapsed) == 0
        np.testing.assert_array_equal(planner._nominal, u)
    assert planner.catch_up(0.21) == 1
    np.testing.assert_array_equal(planner._nominal, np.concatenate([u[1:], u[-1:]]))
    assert planner.catch_up(30.0) == 6  # longer than the horizon: the last command held throughout
    np.testing.assert_array_equal(planner._nominal, np.repeat(u[-1:], 6, axis=0))
