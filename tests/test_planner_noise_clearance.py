"""The propagated covariance carries the GP's predictive variance; obstacle radii cover the path between steps."""

from __future__ import annotations

import numpy as np
import pytest
from cached_models import synthetic_model

from gpmppi.mppi.bundles import ModelBundle
from gpmppi.mppi.dynamics import DYN_GP, GP_GRID, propagate
from gpmppi.mppi.gp_table import TABLE_AXES, collapse_table
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.scenarios import paper_obstacle_scene


def test_propagation_adds_the_likelihood_noise_to_the_latent_variance() -> None:
    model = synthetic_model()
    w = np.array([0.5, 0.3, 0.2])
    g = model.grid()
    table = collapse_table(np.ascontiguousarray(g.table, dtype=np.float32), w)
    controls = np.tile([1.0, 0.5], (10, 1))
    x0 = np.array([0.0, 0.0, 0.0, 0.8, 0.1])
    bundle = ModelBundle(dyn_mode=DYN_GP, theta=model.theta, lateral=np.zeros(2), edd5=model.edd5["grass"],
                         gp_mode=GP_GRID, table=table.reshape(-1, 4), dims=np.array(table.shape[:4], dtype=np.int64),
                         lo=g.lo[TABLE_AXES], inv_step=g.inv_step[TABLE_AXES],
                         **ModelBundle.no_exact(2 * len(model.terrains)), terrain_w=w,
                         **ModelBundle.collapsed_whole())
    args = (bundle.args(), x0, controls, 0.1)
    # called with the argument types the planner passes (noise floats, a start covariance), so this test runs the
    # planner's compiled propagate instead of compiling two more specialisations of it
    zero_cov = np.zeros((5, 5))
    _, cov_latent, var_latent = propagate(*args, 0.0, 0.0, zero_cov)
    _, cov_pred, var_pred = propagate(*args, 2e-3, 5e-3, zero_cov)
    np.testing.assert_allclose(var_pred - var_latent, np.tile([2e-3, 5e-3], (10, 1)), rtol=1e-9, atol=1e-15)
    assert cov_pred[1, 3, 3] == pytest.approx(cov_latent[1, 3, 3] + 2e-3)
    assert cov_pred[-1, 0, 0] > cov_latent[-1, 0, 0]  # the noise reaches the position


def test_planner_covariance_includes_the_weighted_model_noise() -> None:
    model = synthetic_model()
    w = np.array([0.2, 0.3, 0.5])
    cfg = PlannerConfig(samples=64, horizon=5, backend="cpu")
    sc = paper_obstacle_scene()
    grid = Planner(cfg, model).plan(sc.start, sc.task, w)
    exact = Planner(cfg.model_copy(update={"gp_mode": "exact"}), model).plan(sc.start, sc.task, w)
    noise_v = float(w**2 @ model.noise[0::2])
    for r in (grid, exact):  # from the start state (zero covariance) the first step adds latent + noise
        assert r.covariances[1, 3, 3] > noise_v


def test_step_clearance_grows_radii_by_half_a_step() -> None:
    model = synthetic_model()
    sc = paper_obstacle_scene()
    base = {"samples": 32, "horizon": 5, "backend": "cpu", "dynamics": "unicycle"}
    plain = Planner(PlannerConfig(step_clearance=False, **base), model).plan(sc.start, sc.task)
    grown = Planner(PlannerConfig(**base), model).plan(sc.start, sc.task)
    half_step = 0.5 * 0.1 * 2.0  # dt * v_max / 2
    np.testing.assert_allclose(grown.tightened, np.sqrt(plain.tightened**2 + half_step**2), rtol=1e-12)
    # a straight step of v_max dt between two points outside the grown circle never enters the obstacle
    r = sc.task.obstacles[0, 2]
    big = np.sqrt(r**2 + half_step**2)
    assert np.sqrt(big**2 - half_step**2) == pytest.approx(r)
