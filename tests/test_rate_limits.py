"""Rate-limited commands: every sampled sequence's first command, and so the update's and the command sent, changes
from the command in effect by at most the planner's `accel_limits` allow in one step (checked on the kernel's own
samples and on closed loops), the later steps stay free, no limits are the default, limits that never bind change
nothing, and bad limits are refused by name. (CPU and the CUDA simulator agree with limits:
tests/test_planner_cuda.py.)"""

from __future__ import annotations

import numpy as np
import pytest
from cached_models import synthetic_model
from nominal_scoring import kernel_cost, record_nominal_scoring
from pydantic import ValidationError

from gpmppi.models.kinematic_unicycle import kinematic_step
from gpmppi.mppi import backends
from gpmppi.mppi.bundles import TaskBundle
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.scenarios import circle_lane, paper_obstacle_scene, square_lane

W = np.array([0.5, 0.3, 0.2])
DT = 0.1
LIMITS = (2.5, 3.2)  # a Nav2 velocity smoother's defaults [m/s^2, rad/s^2]
STEP = np.array(LIMITS) * DT  # the largest change from one plan's command to the next [m/s, rad/s]
# eps is stored as float32: a command rebuilt from it is off by up to ~1e-7
TOL = 1e-6


def test_every_sampled_first_command_keeps_the_rate_limits_and_the_later_steps_are_free() -> None:
    p = Planner(PlannerConfig(dynamics="gp", backend="cpu", samples=512, horizon=20, seed=4, accel_limits=LIMITS),
                synthetic_model())
    sc = circle_lane()
    x = sc.start.copy()
    for _ in range(3):  # a few cycles in, so that the command in effect is the planner's own
        x = kinematic_step(x, p.plan(x, sc.task, W).control, DT)
    bundle = p.terrain.set_weights(W)
    task = TaskBundle.for_lane(p.kind(sc.task).lane_lookup(sc.task), 1.0, np.ones(21), 1.0)
    sampling = p._sampling(x, p._nominal, np.array([0.5, 0.7]))
    np.testing.assert_array_equal(sampling.u_prev, p._last_control)
    eps, _, _ = backends.rollouts("cpu", bundle, task, sampling, p.kind(sc.task).cost, 512, 0)
    u = p._nominal[None] + eps.astype(np.float64)  # (S, N, 2) the sampled commands
    first = np.abs(u[:, 0] - sampling.u_prev)
    assert np.all(first <= STEP + TOL), first.max(axis=0)
    # the limits bind (the noise, 0.5 and 0.7 a step, asks for more), and within the box still
    assert np.mean(first[:, 1] > STEP[1] - TOL) > 0.3
    assert np.all(u[..., 0] >= -TOL) and np.all(u[..., 0] <= 2.0 + TOL)
    # the later steps are the free white-noise draws: most changes from one step to the next exceed the limits
    assert np.mean(np.abs(np.diff(u[:, 1:, 1], axis=1)) > STEP[1]) > 0.5


def _command_changes(scenario, monkeypatch: pytest.MonkeyPatch, **settings: object) -> np.ndarray:  # noqa: ANN001
    """|change| of the command sent from the one in effect, over 30 cycles of a closed loop [m/s, rad/s]."""
    scored = record_nominal_scoring(monkeypatch)
    sc = scenario()
    p = Planner(PlannerConfig(dynamics="gp", backend="cpu", samples=256, seed=5, **settings), synthetic_model())
    x = sc.start.copy()
    prev = np.clip(x[3:5], [0.0, -np.pi], [2.0, np.pi])  # from rest: the state's own velocities
    changes = []
    for _ in range(30):
        r = p.plan(x, sc.task, W)
        np.testing.assert_array_equal(r.controls[0], r.control)
        changes.append(np.abs(r.control - prev))
        # the nominal sequence's critics, scored with the kernels' clipping, still sum to the kernel's cost of it
        assert r.cost == sum(r.critic_costs.values())
        assert r.cost == pytest.approx(kernel_cost(scored[-1]), rel=1e-9, abs=1e-9)
        prev = r.control
        x = kinematic_step(x, r.control, DT)
    return np.array(changes)


@pytest.mark.parametrize("scenario", [circle_lane, square_lane, paper_obstacle_scene])
def test_the_commands_sent_keep_the_rate_limits(scenario, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: ANN001
    changes = _command_changes(scenario, monkeypatch, accel_limits=LIMITS)
    assert np.all(changes <= STEP + 1e-12), changes.max(axis=0)
    free = _command_changes(scenario, monkeypatch)  # the same loop unlimited oversteps them
    assert np.any(free > STEP), free.max(axis=0)


def test_limits_that_never_bind_change_nothing() -> None:
    def drive(cfg: PlannerConfig) -> np.ndarray:
        sc = circle_lane()
        p = Planner(cfg, synthetic_model())
        x, out = sc.start.copy(), []
        for _ in range(6):
            r = p.plan(x, sc.task, W)
            out.append(r.controls)
            x = kinematic_step(x, r.control, DT)
        return np.array(out)

    base = {"dynamics": "gp", "backend": "cpu", "samples": 128, "seed": 6}
    off = drive(PlannerConfig(**base))
    np.testing.assert_array_equal(drive(PlannerConfig(**base, accel_limits=(1e6, 1e6))), off)
    assert not np.array_equal(drive(PlannerConfig(**base, accel_limits=LIMITS)), off)  # these bind


def test_no_limits_by_default() -> None:
    assert PlannerConfig().accel_limits is None and PlannerConfig(update="paper").accel_limits is None
    p = Planner(PlannerConfig(backend="cpu", samples=8), synthetic_model())
    assert np.all(np.isinf(p._sampling(np.zeros(5), p._nominal, np.ones(2)).rate_step))


@pytest.mark.parametrize("value", [(-1.0, 3.2), (2.5, 0.0), (float("nan"), 3.2), (2.5, float("inf")), "fast", (1.0,)])
def test_bad_rate_limits_are_refused_by_name(value: object) -> None:
    with pytest.raises(ValidationError, match="accel_limits"):
        PlannerConfig(accel_limits=value)


def test_the_sampling_bundle_carries_the_command_in_effect() -> None:
    p = Planner(PlannerConfig(dynamics="unicycle", backend="cpu", samples=8, accel_limits=LIMITS), synthetic_model())
    x = np.array([0.0, 0.0, 0.0, 0.7, -5.0])
    s = p._sampling(x, p._nominal, np.ones(2))
    np.testing.assert_array_equal(s.u_prev, [0.7, -np.pi])  # before any plan: the state's velocities, in the box
    np.testing.assert_array_equal(s.rate_step, STEP)
    r = p.plan(x, circle_lane().task, W)
    np.testing.assert_array_equal(p._sampling(x, p._nominal, np.ones(2)).u_prev, r.control)
