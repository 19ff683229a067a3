"""The terrain-weight estimator recovers known weights; short histories and solver trouble keep the old ones."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest
from cached_models import synthetic_model

from gpmppi.gp.exact import ExactPredictor
from gpmppi.gp.model_file import GPModel
from gpmppi.models.dynamic_unicycle import velocity_step_exact
from gpmppi.terrain.least_squares import TerrainEstimator


@lru_cache(maxsize=1)
def _model() -> GPModel:
    return synthetic_model()


def _history(model: GPModel, w_true: np.ndarray, steps: int, seed: int, noise: float = 0.0):
    """Synthetic (state, command, next state): exact nominal step plus the w_true mixture of GP means."""
    pred = ExactPredictor(model)
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(steps):
        x = np.array([rng.normal(), rng.normal(), rng.uniform(-3, 3), rng.uniform(0, 2), rng.uniform(-2, 2)])
        u = np.array([rng.uniform(0, 2), rng.uniform(-2, 2)])
        v1, w1 = velocity_step_exact(model.theta, x[3:4], x[4:5], u[0:1], u[1:2], model.dt)
        mean, _ = pred.predict(np.array([[u[0], u[1], x[3], x[4]]]), with_var=False)
        x1 = x.copy()
        x1[3] = v1[0] + mean[0, 0::2] @ w_true + noise * rng.normal()
        x1[4] = w1[0] + mean[0, 1::2] @ w_true + noise * rng.normal()
        rows.append((x, u, x1))
    return rows


@pytest.mark.parametrize("w_true", [[0.6, 0.0, 0.4], [0.0, 1.0, 0.0], [0.2, 0.3, 0.5]])
def test_recovers_known_weights(w_true: list[float]) -> None:
    model = _model()
    est = TerrainEstimator(model, history=20, gamma=1e-6)
    for row in _history(model, np.array(w_true), 20, seed=1):
        est.observe(*row)
    e = est.estimate()
    assert e.ok, e.message
    np.testing.assert_allclose(e.weights, w_true, atol=5e-3)
    assert e.weights.sum() == pytest.approx(1.0) and np.all(e.weights >= 0)
    assert e.residual < 1e-6


def test_recovers_weights_under_measurement_noise_and_tracks_a_change() -> None:
    model = _model()
    est = TerrainEstimator(model, history=30, gamma=1e-5)
    for row in _history(model, np.array([1.0, 0.0, 0.0]), 30, seed=2, noise=2e-4):
        est.observe(*row)
    assert np.argmax(est.estimate().weights) == 0
    # the terrain changes: once the history has turned over, the estimate follows
    for row in _history(model, np.array([0.0, 0.0, 1.0]), 30, seed=3, noise=2e-4):
        est.observe(*row)
    e = est.estimate()
    assert e.ok and e.weights[2] > 0.9


def test_l1_term_holds_weights_near_the_previous_ones() -> None:
    model = _model()
    rows = _history(model, np.array([0.0, 0.0, 1.0]), 20, seed=4)
    loose = TerrainEstimator(model, history=20, gamma=1e-6)
    # gamma is in units of the noise-normalised mean squared residual: the synthetic terrains differ by many
    # noise stds per step, so holding the weights takes a gamma of that order
    sticky = TerrainEstimator(model, history=20, gamma=100.0)
    for row in rows:
        loose.observe(*row)
        sticky.observe(*row)
    moved_loose = np.abs(loose.estimate().weights - 1 / 3).sum()
    moved_sticky = np.abs(sticky.estimate().weights - 1 / 3).sum()
    assert moved_sticky < 0.05 < moved_loose


def test_default_gamma_moves_the_weights_at_the_models_noise_level() -> None:
    # the fit is normalised by the model's noise, so the default gamma lets data scattered by that noise move the
    # weights all the way (an unnormalised fit of such residuals is ~1e-3 and a gamma of 0.1 would pin them)
    model = _model()
    noise_std = float(np.sqrt(model.noise.mean()))
    est = TerrainEstimator(model)
    for row in _history(model, np.array([0.0, 1.0, 0.0]), 20, seed=7, noise=noise_std):
        est.observe(*row)
    e = est.estimate()
    assert e.ok and e.weights[1] > 0.9


def test_fit_is_a_mean_per_step_so_gamma_does_not_depend_on_the_history_length() -> None:
    model = _model()
    rows = _history(model, np.array([0.1, 0.2, 0.7]), 10, seed=8, noise=0.02)
    once = TerrainEstimator(model, history=10, gamma=1.0)
    twice = TerrainEstimator(model, history=20, gamma=1.0)
    for row in rows:
        once.observe(*row)
        twice.observe(*row)
        twice.observe(*row)
    w_once, w_twice = once.estimate().weights, twice.estimate().weights
    assert np.abs(w_once - 1 / 3).sum() > 0.1  # the weights moved, and
    np.testing.assert_allclose(w_twice, w_once, atol=1e-4)  # the same data counted twice moves them the same


def test_short_history_keeps_previous_weights() -> None:
    model = _model()
    est = TerrainEstimator(model, history=10, gamma=0.1, min_history=3)
    est.reset(np.array([0.2, 0.3, 0.5]))
    for row in _history(model, np.array([1.0, 0.0, 0.0]), 2, seed=5):
        est.observe(*row)
    e = est.estimate()
    assert not e.ok and "too short" in e.message
    np.testing.assert_array_equal(e.weights, [0.2, 0.3, 0.5])


def test_problem_is_built_once_and_is_dpp() -> None:
    est = TerrainEstimator(_model(), history=8)
    problem = est._problem
    assert problem.is_dpp()
    for row in _history(_model(), np.array([0.3, 0.3, 0.4]), 12, seed=6):
        est.observe(*row)
        est.estimate()
    assert est._problem is problem and len(est) == 8


def test_bad_observations_are_rejected_with_the_field_named() -> None:
    est = TerrainEstimator(_model())
    x = np.zeros(5)
    with pytest.raises(ValueError, match="state"):
        est.observe(np.array([0, 0, 0, np.nan, 0]), np.zeros(2), x)
    with pytest.raises(ValueError, match="command"):
        est.observe(x, np.zeros(3), x)
    with pytest.raises(ValueError, match="next_state"):
        est.observe(x, np.zeros(2), np.full(5, np.inf))
    with pytest.raises(ValueError, match="gamma"):
        TerrainEstimator(_model(), gamma=-1.0)
    with pytest.raises(ValueError, match="simplex"):
        est.reset(np.array([0.5, 0.6, 0.2]))
    assert len(est) == 0
