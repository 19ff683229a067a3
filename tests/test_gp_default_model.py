"""The shipped default model: loads, its grid is accurate, and it improves on the nominal model on
fresh plant data it has never seen (a different seed from the one it was trained on)."""

from __future__ import annotations

import numpy as np
import pytest
from cached_models import shipped_model

from gpmppi.gp.exact import ExactPredictor
from gpmppi.gp.grid import GridPredictor
from gpmppi.gp.model_file import DEFAULT_MODEL_PATH
from gpmppi.gp.train import residual_targets


@pytest.fixture(scope="module")
def model():
    return shipped_model()


def test_default_model_is_shipped_small_and_complete(model) -> None:
    assert DEFAULT_MODEL_PATH.stat().st_size < 10e6
    assert set(model.terrains) == {"tile", "asphalt", "grass"}
    assert model.has_stored_grid() and model.grid().nodes >= 20
    assert model.train_x.shape[0] >= 200


def test_shipped_grid_matches_exact_within_one_percent(model) -> None:
    x = np.random.default_rng(11).uniform(model.domain_lo, model.domain_hi, (4000, 4))
    em, ev = ExactPredictor(model).predict(x)
    gm, gv = GridPredictor(model).predict(x)
    rel_mean = np.sqrt(((gm - em) ** 2).mean(0)) / np.sqrt((em**2).mean(0))
    rel_var = np.sqrt(((gv - ev) ** 2).mean(0)) / np.sqrt((ev**2).mean(0))
    assert np.all(rel_mean < 0.01), dict(zip(model.tasks, rel_mean, strict=True))
    assert np.all(rel_var < 0.05), dict(zip(model.tasks, rel_var, strict=True))


def test_default_model_beats_nominal_on_fresh_plant_data(model) -> None:
    from gpmppi.plant.excitation import simulate_dataset
    from gpmppi.plant.terrains import load_terrains

    runs = simulate_dataset(load_terrains(None), list(model.terrains), distance=150.0, seed=12345)
    for name, run in runs.items():
        v, w = run.state[:, 3], run.state[:, 4]
        x = np.column_stack([run.command[:-1], v[:-1], w[:-1]])
        res = residual_targets(model.theta, x, np.column_stack([v[1:], w[1:]]), model.dt)
        for predictor in (ExactPredictor(model), GridPredictor(model)):
            mean, _ = predictor.predict(x)
            for o, out in enumerate(("v", "omega")):
                t = model.task_index(name, out)
                rmse_nominal = np.sqrt(np.mean(res[:, o] ** 2))
                rmse_gp = np.sqrt(np.mean((res[:, o] - mean[:, t]) ** 2))
                assert rmse_gp < 0.8 * rmse_nominal, (type(predictor).__name__, name, out, rmse_gp, rmse_nominal)
