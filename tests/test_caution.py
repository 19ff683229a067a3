"""The planner's caution on unknown ground (gpmppi/mppi/caution.py): applied while the terrain service says the
ground is unknown and only then; the lane's speed target scaled, a goal approached at a bounded speed, and the chance
constraints tightened by the extra residual variance in a real plan."""

from __future__ import annotations

import numpy as np
import pytest
from cached_models import shipped_model

from gpmppi.mppi.caution import cautious_task
from gpmppi.mppi.cycle import Planned, PlannerCycle
from gpmppi.mppi.cycle_config import CycleConfig
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.scenarios import circle_lane, paper_obstacle_scene
from gpmppi.tasks import GoalTask, LaneTask

NS = 1_000_000_000
LANE = LaneTask(np.array([[0.0, 0.0], [100.0, 0.0]]), half_width=1.0, speed_target=1.5, closed=False)


class Recording:
    """A planner that records the task and extra variance of each plan."""

    def __init__(self) -> None:
        self.extra_variance = (0.0, 0.0)
        self.seen: list[tuple[float, tuple[float, float]]] = []

    def plan(self, state, task, weights=None, state_cov=None, delay_s=0.0):  # noqa: ANN001, ANN201
        self.seen.append((task.speed_target, self.extra_variance))

        class R:
            control = np.array([1.0, 0.0])
            states = np.zeros((3, 5))
        return R()

    def prepare(self, weights) -> None:  # noqa: ANN001
        pass

    def reset(self) -> None:
        pass


def test_caution_applies_only_while_the_ground_is_unknown() -> None:
    planner = Recording()
    cfg = CycleConfig(unknown_speed_scale=0.8, unknown_residual_std=(0.03, 0.05))
    cycle = PlannerCycle(planner, LANE, cfg, 2, ["asphalt", "grass"], clock=lambda: 0.0)
    x = np.array([1.0, 0.0, 0.0, 1.0, 0.0])
    for k, unknown in enumerate([False, True, True, False]):
        assert cycle.on_weights([0.5, 0.5], 0.1 * k, unknown_active=unknown)
        assert isinstance(cycle.on_state(x, k * NS // 10, 0.1 * k, k * NS // 10), Planned)
    assert planner.seen[0] == (1.5, (0.0, 0.0))
    assert planner.seen[1] == planner.seen[2] == (1.5 * 0.8, (0.03 ** 2, 0.05 ** 2))
    assert planner.seen[3] == (1.5, (0.0, 0.0))
    assert [e.name for e in cycle.drain_events()] == ["caution_on", "caution_off"]
    # the task itself is not changed: the caution is a view of it for the plan
    assert cycle.task is LANE and LANE.speed_target == 1.5
    # switched off by the settings, the flag changes nothing
    off = PlannerCycle(Recording(), LANE, CycleConfig(unknown_caution=False), 2, clock=lambda: 0.0)
    off.on_weights([0.5, 0.5], 0.0, unknown_active=True)
    off.on_state(x, 0, 0.0, 0)
    assert off.planner.seen == [(1.5, (0.0, 0.0))] and not off.unknown_active  # type: ignore[attr-defined]


def test_the_extra_variance_tightens_a_real_plans_lane() -> None:
    sc = circle_lane()
    planner = Planner(PlannerConfig(samples=64, horizon=20, seed=0), shipped_model())
    w = np.array([0.0, 1.0, 0.0])
    plain = planner.plan(sc.start, sc.task, w).tightened
    planner.reset()
    planner.extra_variance = (0.03 ** 2, 0.03 ** 2)
    careful = planner.plan(sc.start, sc.task, w).tightened
    # the same start, a narrower lane at the end of the horizon (the extra variance grows along it)
    assert careful[0] == plain[0] and careful[-1] < plain[-1] - 0.05


def test_a_goal_is_approached_slower_while_the_ground_is_unknown() -> None:
    """Glare ice's scene collisions (docs/new_ground.md, "Glare ice in the scene"): the robot came to the goal too fast
    to turn into it on ground that grips less than any trained one, circled it and slid into an obstacle. While the
    ground is unknown by its grip a goal task's commanded speed is bounded, the lower the nearer the goal; the task
    itself is unchanged."""
    sc = paper_obstacle_scene()
    cfg = CycleConfig()
    planner = Planner(PlannerConfig(samples=64, horizon=20, seed=0), shipped_model())
    cycle = PlannerCycle(planner, sc.task, cfg, 3, clock=lambda: 0.0)
    x = np.array([6.9, 3.6, 1.0, 1.3, 0.4])  # 1.4 m before the goal at 1.3 m/s: where a colliding trial turned in
    speeds = {}
    # known; unknown by its grip (the free-run channel, as glare ice); unknown by its drag (the one-step one, as sand)
    for unknown, channel in ((False, ""), (True, "free-run"), (True, "one-step")):
        planner.reset()
        assert cycle.on_weights([1 / 3, 1 / 3, 1 / 3], 0.0, unknown_active=unknown, unknown_channel=channel)
        for k in range(8):  # a few iterations from there: the warm start settles
            out = cycle.on_state(x, k * NS // 10, 0.1 * k, k * NS // 10)
            assert isinstance(out, Planned)
        assert cycle.unknown_active == unknown and cycle.unknown_grip == (channel == "free-run")
        speeds[channel] = out.result.controls[:, 0]
        assert cycle.on_weights([1 / 3, 1 / 3, 1 / 3], 0.0)  # known again between the cases
    assert cfg.unknown_goal_speed is not None
    bound = cautious_task(sc.task, cfg, grip=True).speed_bound(out.result.states[0, :2])
    assert bound is not None and bound < 1.2
    assert speeds["free-run"].max() <= bound + 1e-12  # every step of the plan, not only the command sent
    assert speeds[""].max() > bound + 0.2  # without the caution it plans faster there
    assert speeds["one-step"].max() > bound + 0.2  # a ground that drags still turns: no bound
    assert cycle.task is sc.task and sc.task.approach_speed is None


def test_a_loss_of_grip_stays_the_alarm_s_until_it_ends() -> None:
    """The free-run channel holds its alarm across straights, where the one-step channel's probability may be the
    larger: the grip stays unknown until the ground is known again, and not longer."""
    cycle = PlannerCycle(Recording(), LANE, CycleConfig(), 2, clock=lambda: 0.0)
    steps = [(True, "one-step", False), (True, "free-run", True), (True, "one-step", True), (True, "", True),
             (False, "", False), (True, "one-step", False)]
    for active, channel, grip in steps:
        cycle.on_weights([0.5, 0.5], 0.0, unknown_active=active, unknown_channel=channel)
        assert (cycle.unknown_active, cycle.unknown_grip) == (active, grip)


def test_the_goal_bound_rises_with_the_distance_and_leaves_plans_below_it_unchanged() -> None:
    task = GoalTask(np.array([7.0, 5.0]), tolerance=0.5, approach_speed=0.6, approach_decel=0.5)
    assert task.speed_bound(np.array([7.2, 5.0])) == pytest.approx(0.6)  # within the tolerance
    assert task.speed_bound(np.array([7.0, 2.5])) == pytest.approx(np.sqrt(0.36 + 2 * 0.5 * 2.0))
    assert GoalTask(np.array([7.0, 5.0])).speed_bound(np.zeros(2)) is None
    with pytest.raises(ValueError, match="approach_speed"):
        GoalTask(np.array([7.0, 5.0]), approach_speed=0.0)
    # a bound above the planner's speed limit where the plan starts: the plan is the one without a bound, bit for bit
    sc = paper_obstacle_scene()
    far = GoalTask(sc.task.goal, sc.task.tolerance, sc.task.obstacles, approach_speed=1.0, approach_decel=2.0)
    plans = []
    for task in (sc.task, far):
        planner = Planner(PlannerConfig(samples=64, horizon=20, seed=0), shipped_model())
        plans.append(planner.plan(sc.start, task, np.full(3, 1 / 3)))
    assert far.speed_bound(sc.start[:2]) > 2.0
    assert plans[0].controls.tobytes() == plans[1].controls.tobytes() and plans[0].cost == plans[1].cost
