"""The effective sample size each plan reports: Kish's 1 / sum(w^2) of the update's softmax weights, checked against
scipy's softmax of the rollout costs; carried by the Plan message."""

from __future__ import annotations

import numpy as np
import pytest
from cached_models import synthetic_model
from scipy.special import softmax

from gpmppi.mppi.backends import effective_sample_size
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.scenarios import circle_lane
from schemas.messages import Plan
from services.planner_outputs import plan_message


def test_effective_sample_size_of_known_weights() -> None:
    assert effective_sample_size(np.full(8, 1 / 8)) == pytest.approx(8.0)
    assert effective_sample_size(np.eye(5)[2]) == pytest.approx(1.0)
    assert effective_sample_size(np.array([0.5, 0.5, 0.0, 0.0])) == pytest.approx(2.0)
    assert effective_sample_size(np.zeros(4)) == 0.0  # every cost infinite: no update


@pytest.mark.parametrize("temperature", [1.0, 50.0])
def test_plans_report_the_effective_samples_of_their_update(temperature: float) -> None:
    sc = circle_lane()
    samples = 64
    cfg = PlannerConfig(dynamics="edd5", backend="cpu", samples=samples, sample_output=samples, seed=3,
                        temperature=temperature, update="paper")
    p = Planner(cfg, synthetic_model())
    x = sc.start.copy()
    for _ in range(3):
        r = p.plan(x, sc.task, None)
        w = softmax(-np.asarray(r.sample_costs) / temperature)  # every rollout's cost is reported (sample_output)
        assert r.effective_samples == pytest.approx(1.0 / np.sum(w * w), rel=1e-9)
        assert 1.0 <= r.effective_samples <= samples
        x = r.states[1].copy()
    # a hotter softmax spreads the update over more rollouts
    if temperature > 1.0:
        cold = Planner(cfg.model_copy(update={"temperature": 1.0}), synthetic_model()).plan(sc.start, sc.task, None)
        hot = Planner(cfg, synthetic_model()).plan(sc.start, sc.task, None)
        assert hot.effective_samples > cold.effective_samples


def test_plan_message_carries_the_effective_samples() -> None:
    sc = circle_lane()
    r = Planner(PlannerConfig(dynamics="unicycle", backend="cpu", samples=32, seed=1), synthetic_model()).plan(
        sc.start, sc.task, None)
    msg = plan_message(r, 0, sc.task, 8)
    decoded = Plan.model_validate_json(msg.model_dump_json())
    assert decoded.effective_samples == pytest.approx(r.effective_samples)
    # a recording made before the field existed decodes without it
    old = msg.model_dump(mode="json")
    old.pop("effective_samples")
    assert Plan.model_validate(old).effective_samples is None
