"""The planner's caution on unknown ground (gpmppi/mppi/caution.py): applied while the terrain service says the
ground is unknown and only then; the lane's speed target scaled, and the chance constraints tightened by the extra
residual variance in a real plan."""

from __future__ import annotations

import numpy as np

from gpmppi.gp.model_file import load_default_model
from gpmppi.mppi.cycle import Planned, PlannerCycle
from gpmppi.mppi.cycle_config import CycleConfig
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.scenarios import circle_lane
from gpmppi.tasks import LaneTask

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
    planner = Planner(PlannerConfig(samples=64, horizon=20, seed=0), load_default_model())
    w = np.array([0.0, 1.0, 0.0])
    plain = planner.plan(sc.start, sc.task, w).tightened
    planner.reset()
    planner.extra_variance = (0.03 ** 2, 0.03 ** 2)
    careful = planner.plan(sc.start, sc.task, w).tightened
    # the same start, a narrower lane at the end of the horizon (the extra variance grows along it)
    assert careful[0] == plain[0] and careful[-1] < plain[-1] - 0.05
