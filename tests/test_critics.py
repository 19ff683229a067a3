"""Named critics: each plan's per-critic costs of its nominal sequence sum to its cost (every model, both tasks);
a weight reaches its critic by name, and a zero weight silences that critic alone."""

from __future__ import annotations

import numpy as np
import pytest
from cached_models import synthetic_model
from nominal_scoring import kernel_cost, record_nominal_scoring

from gpmppi.mppi import backends
from gpmppi.mppi.bundles import CRITICS, TaskBundle
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.scenarios import circle_lane, paper_obstacle_scene

W = np.array([0.5, 0.3, 0.2])
VARIANTS = {
    "edd5": {"dynamics": "edd5"},
    "unicycle": {"dynamics": "unicycle"},
    "gp-simplex": {"dynamics": "gp"},
    "gp-multilinear": {"dynamics": "gp", "grid_interpolation": "multilinear"},
    "gp-exact": {"dynamics": "gp", "gp_mode": "exact"},
}
LANE_ONLY = {"deviation", "slip", "lane_exit", "speed"}
GOAL_ONLY = {"collision", "costmap", "goal", "terminal"}


@pytest.fixture(scope="module")
def model():  # noqa: ANN201 - a GPModel
    return synthetic_model()


@pytest.mark.parametrize("task_name", ["lane", "goal"])
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_critic_costs_sum_to_the_plan_cost(
    model, variant: str, task_name: str, monkeypatch: pytest.MonkeyPatch,  # noqa: ANN001
) -> None:
    """The plan's cost is the sum of its critics' costs, and that sum is what the rollout kernel gives the same
    nominal sequence (the plan scores it once, per critic; the kernel here, as it scores every sample)."""
    scored = record_nominal_scoring(monkeypatch)
    scenario = circle_lane() if task_name == "lane" else paper_obstacle_scene()
    p = Planner(PlannerConfig(backend="cpu", samples=64, seed=5, **VARIANTS[variant]), model)
    x = scenario.start.copy()
    for _ in range(3):
        r = p.plan(x, scenario.task, W)
        assert list(r.critic_costs) == list(CRITICS)
        assert r.cost == sum(r.critic_costs.values())
        # the exact GP's likelihood noise adds the same to every rollout: the plan adds it after the kernels
        variance_w = p.kind(scenario.task).cost.weights["variance"]
        noise = p.config.horizon * variance_w * sum(p.terrain.exact_noise_var(W))
        # the serial evaluation reads the float32 GP table in its own order, so the grid GP's rollout differs in
        # the float32 roundings (~1e-9 of the cost); a critic missing or counted twice is off by far more
        assert r.cost == pytest.approx(kernel_cost(scored[-1]) + noise, rel=1e-8, abs=1e-10)
        unused = GOAL_ONLY if task_name == "lane" else LANE_ONLY
        assert all(r.critic_costs[name] == 0.0 for name in unused)
        assert r.critic_costs["variance"] > 0.0 if variant.startswith("gp") else r.critic_costs["variance"] == 0.0
        x = r.states[1].copy()
    used = {"deviation", "speed"} if task_name == "lane" else {"goal", "terminal"}
    assert all(r.critic_costs[name] > 0.0 for name in used), r.critic_costs


def _bundles(model, task_name: str) -> tuple:  # noqa: ANN001
    """A GP planner's model, task and nominal sampling bundles after one plan (the lane planned to leave it)."""
    scenario = circle_lane() if task_name == "lane" else paper_obstacle_scene()
    # the paper's update: its first plan wanders enough to leave the narrowed lane (the smooth one stays inside)
    p = Planner(PlannerConfig(backend="cpu", samples=64, seed=5, update="paper"), model)
    r = p.plan(scenario.start, scenario.task, W)
    bundle = p.terrain.set_weights(W)
    task = scenario.task
    if task_name == "lane":
        # a half-width the plan leaves, so that the lane-exit indicator counts too
        lane = p.kind(task).lane_lookup(task)
        t = TaskBundle.for_lane(lane, 0.3, np.full(r.tightened.shape[0], 0.02), task.speed_target)
    else:
        t = TaskBundle.for_goal(task.goal, task.obstacles, r.tightened, p.kind(task).goal_field(task, scenario.start))
    return p, bundle, t, p._sampling(r.states[0], r.controls, np.zeros(2)), p.kind(task).cost


@pytest.mark.parametrize("task_name", ["lane", "goal"])
def test_a_zero_weight_silences_its_own_critic_only(model, task_name: str) -> None:  # noqa: ANN001
    p, bundle, task, sampling, base = _bundles(model, task_name)
    full = backends.critic_costs(bundle, task, sampling, base)
    used = [name for name in CRITICS if full[name] != 0.0]
    assert set(used) >= ({"variance"} | (LANE_ONLY if task_name == "lane" else {"goal", "terminal"})), full
    for name in used:
        cost = base.with_weight(name, 0.0)
        got = backends.critic_costs(bundle, task, sampling, cost)
        assert got[name] == 0.0
        assert {k: v for k, v in got.items() if k != name} == {k: v for k, v in full.items() if k != name}, name
        # and the kernel's total drops by exactly that critic's share
        _, total, _ = backends.rollouts("cpu", bundle, task, sampling, cost, 1, 0)
        _, total_full, _ = backends.rollouts("cpu", bundle, task, sampling, base, 1, 0)
        assert total_full[0] - total[0] == pytest.approx(full[name], abs=1e-8 * total_full[0])


def test_weights_reach_their_critics_by_name(model) -> None:  # noqa: ANN001
    config = PlannerConfig(critics={name: {"weight": float(i + 1)} for i, name in enumerate(CRITICS)})
    assert config.critic_weights("lane") == {name: float(i + 1) if name not in GOAL_ONLY else 0.0
                                             for i, name in enumerate(CRITICS)}
    assert config.cost_bundle("goal").weights == config.critic_weights("goal")
    p, bundle, task, sampling, base = _bundles(model, "lane")
    full = backends.critic_costs(bundle, task, sampling, base)
    for name in ("deviation", "slip", "speed", "variance", "lane_exit"):
        doubled = base.with_weight(name, 2.0 * base.weights[name])
        got = backends.critic_costs(bundle, task, sampling, doubled)
        assert got[name] == pytest.approx(2.0 * full[name], rel=1e-12)
        assert all(got[k] == full[k] for k in CRITICS if k != name)
