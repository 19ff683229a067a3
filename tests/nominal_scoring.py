"""What a plan scored as its nominal sequence, recorded, and the rollout kernel's cost of the same sequence: the plan
scores its nominal once, per critic (`backends.critic_costs`), and takes the sum as its cost; these check that sum
against the kernel, which adds the same terms step by step for every sample."""

from __future__ import annotations

import pytest

from gpmppi.mppi import backends


def record_nominal_scoring(monkeypatch: pytest.MonkeyPatch) -> list[tuple]:
    """From now on, each plan's `backends.critic_costs` call appends its bundles (model, task, sampling, cost)."""
    scored: list[tuple] = []
    split = backends.critic_costs

    def critic_costs(*bundles):  # noqa: ANN002, ANN202 - the plan's call, recorded
        scored.append(bundles)
        return split(*bundles)

    monkeypatch.setattr(backends, "critic_costs", critic_costs)
    return scored


def kernel_cost(bundles: tuple) -> float:
    """The CPU rollout kernel's cost of the recorded nominal sequence (one sample, no noise)."""
    model, task, sampling, cost = bundles
    _, costs, _ = backends.rollouts("cpu", model, task, sampling, cost, 1, 0)
    return float(costs[0])
