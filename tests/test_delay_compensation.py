"""Delay compensation: the planner plans from the state its command will meet, predicted with the command still
in effect; the prediction against closed forms and the one-step propagation, and the closed-loop effect."""

from __future__ import annotations

import numpy as np
import pytest
from cached_models import shipped_model

from gpmppi.evaluation.closed_loop import ClosedLoopConfig, run_closed_loop
from gpmppi.evaluation.metrics import lane_rmse_mm
from gpmppi.mppi.dynamics import predict_ahead, propagate
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.plant.physics import PhysicsPlant
from gpmppi.plant.terrains import load_terrains
from gpmppi.scenarios import circle_lane
from gpmppi.terrain.least_squares import TerrainEstimator


def _model(planner: Planner, w: np.ndarray) -> tuple:
    """The model bundle's tuple `predict_ahead` / `propagate` take, as the planner passes it."""
    model = planner.terrain.set_weights(w)
    return model.args()


def test_unicycle_prediction_follows_the_arc_of_the_held_command() -> None:
    planner = Planner(PlannerConfig(dynamics="unicycle"), shipped_model())
    w = np.full(3, 1 / 3)
    v, om, d = 1.2, 0.8, 0.25
    x0 = np.array([1.0, -2.0, 0.3, 0.0, 0.0])
    x, cov = predict_ahead(_model(planner, w), x0, np.eye(5) * 1e-4, np.array([v, om]), d, 0.1)
    yaw = 0.3 + om * d
    arc = [1.0 + v / om * (np.sin(yaw) - np.sin(0.3)), -2.0 - v / om * (np.cos(yaw) - np.cos(0.3))]
    # explicit Euler over 10 ms substeps: within v * omega * h * d / 2 ~ 1.2 mm of the exact arc
    np.testing.assert_allclose(x[:2], arc, atol=2e-3)
    assert x[2] == pytest.approx(yaw) and x[3:] == pytest.approx([v, om])
    np.testing.assert_array_equal(cov, np.eye(5) * 1e-4)  # a model without a GP adds no uncertainty


def test_gp_prediction_of_one_substep_is_one_propagation_step() -> None:
    planner = Planner(PlannerConfig(), shipped_model())
    w = np.array([0.6, 0.3, 0.1])
    model = _model(planner, w)
    x0 = np.array([0.5, 0.2, -0.4, 0.9, 0.3])
    u = np.array([1.1, -0.2])
    cov0 = np.diag([1e-4, 2e-4, 1e-5, 3e-4, 1e-4])
    dt = 0.01  # one substep, the whole residual: exactly `propagate`'s step
    x, cov = predict_ahead(model, x0, cov0, u, dt, dt)
    states, covs, _ = propagate(model, x0, u[None, :], dt, 0.0, 0.0, cov0)
    np.testing.assert_allclose(x, states[1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(cov, covs[1], rtol=0, atol=1e-15)


def test_gp_prediction_spreads_the_step_residual_over_the_delay() -> None:
    planner = Planner(PlannerConfig(), shipped_model())
    w = np.array([0.0, 1.0, 0.0])
    model = _model(planner, w)
    x0 = np.array([0.0, 0.0, 0.0, 1.0, 0.5])
    u = np.array([1.0, 0.5])
    # over one whole planner step the ten substeps add the step's residual (as one Euler step adds it) to within
    # the residual's change along the way; the pose integrates the velocities finer than one Euler step
    x, cov = predict_ahead(model, x0, np.zeros((5, 5)), u, 0.1, 0.1)
    states, covs, _ = propagate(model, x0, u[None, :], 0.1, 0.0, 0.0, np.zeros((5, 5)))
    assert abs(x[3] - states[1, 3]) < 0.02 and abs(x[4] - states[1, 4]) < 0.02
    assert np.linalg.norm(x[:2] - states[1, :2]) < 0.01
    # the velocity variance added is the step's, less what the velocity's own decay (J[3, 3] = 1 - a h) takes off
    # the part added early (one propagation step adds it all after the Jacobian), and it reaches the position
    assert 0.6 * covs[1, 3, 3] < cov[3, 3] < covs[1, 3, 3] and cov[0, 0] > 0.0
    # half the delay, about half the variance (less decay)
    _, half = predict_ahead(model, x0, np.zeros((5, 5)), u, 0.05, 0.1)
    assert 0.5 * cov[3, 3] < half[3, 3] < 0.65 * cov[3, 3]


def test_planner_plans_from_the_predicted_state_with_the_last_command() -> None:
    model = shipped_model()
    task = circle_lane().task
    x0 = np.array([8.25, 0.0, np.pi / 2, 0.8, 0.1])
    p = Planner(PlannerConfig(samples=256, seed=3), model)
    same = Planner(PlannerConfig(samples=256, seed=3), model)
    # no delay: exactly the plan without the argument
    a, b = p.plan(x0, task, delay_s=0.0), same.plan(x0, task)
    np.testing.assert_array_equal(a.controls, b.controls)
    # with a delay: the plan starts where the last command takes the robot by then
    w = np.full(3, 1 / 3)
    expected, _ = predict_ahead(_model(p, w), x0, p._default_state_cov, a.control, 0.08, 0.1)
    r = p.plan(x0, task, delay_s=0.08)
    np.testing.assert_allclose(r.states[0], expected, atol=1e-12)
    assert r.states[0][1] > x0[1] + 0.05  # it moved ahead along the lane (+y at this point), ~0.8 m/s * 80 ms
    # after a reset there is no last command: the state's own velocities are held
    p.reset()
    held, _ = predict_ahead(_model(p, w), x0, p._default_state_cov, x0[3:5].copy(), 0.08, 0.1)
    np.testing.assert_allclose(p.plan(x0, task, delay_s=0.08).states[0], held, atol=1e-12)


@pytest.mark.parametrize("bad", [-0.01, float("nan"), float("inf"), 100.0])
def test_an_impossible_delay_is_refused_naming_it(bad: float) -> None:
    p = Planner(PlannerConfig(samples=64), shipped_model())
    with pytest.raises(ValueError, match="delay_s"):
        p.plan(np.array([8.25, 0.0, np.pi / 2, 0.0, 0.0]), circle_lane().task, delay_s=bad)


@pytest.mark.slow
def test_compensation_recovers_tracking_under_command_latency() -> None:
    """150 ms of command latency on the circle (physics plant, asphalt): planning for the state the command meets
    tracks markedly better than planning from the measured one (measured: 30.6 against 46.6 mm, 4 seeds)."""
    model = shipped_model()
    sc = circle_lane()

    def rmse(compensate: bool, seed: int) -> float:
        traj = run_closed_loop(
            Planner(PlannerConfig(seed=seed), model), PhysicsPlant(load_terrains(None), "asphalt", seed=seed),
            sc.task, sc.start, len(model.terrains),
            ClosedLoopConfig(time_limit_s=10.0, latency_s=0.15, compensate_latency=compensate),
            estimator=TerrainEstimator(model),
        )
        return lane_rmse_mm(traj.true_states[:, :2], sc.task.centerline, closed=True)

    with_comp = [rmse(True, s) for s in range(3)]
    without = [rmse(False, s) for s in range(3)]
    assert np.mean(with_comp) < 0.8 * np.mean(without), (with_comp, without)
