"""The terrain estimator on the paper's real residual table (`gpmppi evaluate terrain-real-data`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cached_models import shipped_model
from typer.testing import CliRunner

from gpmppi.gp.exact import ExactPredictor
from gpmppi.terrain.real_data import ONE_STEP_ONLY, ResidualTable, read_residual_table, window_scores
from gpmppi.terrain.settings import EstimatorConfig
from tools.cli import app

runner = CliRunner()


def _table_of_gp_means(n: int = 120, seed: int = 3) -> ResidualTable:
    """Rows whose every ground's residual is exactly that ground's GP mean (plus a little noise)."""
    model = shipped_model()
    rng = np.random.default_rng(seed)
    inputs = np.column_stack([rng.uniform(0.5, 1.8, n), rng.uniform(-1.5, 1.5, n), rng.uniform(0.4, 1.8, n),
                              rng.uniform(-1.5, 1.5, n)])
    mean = ExactPredictor(model).predict(inputs)[0].reshape(n, len(model.terrains), 2)
    residuals = {t: mean[:, i] + rng.normal(0.0, [0.005, 0.01], (n, 2)) for i, t in enumerate(model.terrains)}
    return ResidualTable(inputs, residuals)


def test_windows_of_a_grounds_own_predictions_pick_that_ground() -> None:
    model = shipped_model()
    table = _table_of_gp_means()
    scores = window_scores(model, table, window=30, trials=8, seed=0, config=EstimatorConfig(**ONE_STEP_ONLY))
    assert set(scores) == set(model.terrains)
    for ground, s in scores.items():
        assert s["top_fraction"] >= 0.75, (ground, s)
        assert s["true_weight_mean"] > 0.5, (ground, s)


def test_a_table_with_another_grounds_residuals_does_not_pick_the_label() -> None:
    """Swap two grounds' residuals: the labels now point at the wrong rows, so the 'true' weight collapses."""
    model = shipped_model()
    table = _table_of_gp_means()
    a, b = model.terrains[0], model.terrains[1]
    swapped = ResidualTable(table.inputs, {**table.residuals, a: table.residuals[b], b: table.residuals[a]})
    scores = window_scores(model, swapped, window=30, trials=8, seed=0, config=EstimatorConfig(**ONE_STEP_ONLY))
    assert scores[a]["top_fraction"] <= 0.25 and scores[b]["top_fraction"] <= 0.25, scores


def test_malformed_table_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("gp_ip_cmd_lin,gp_ip_cmd_ang\n1.0,0.2\n")
    with pytest.raises(ValueError, match="expected columns"):
        read_residual_table(bad)
    result = runner.invoke(app, ["evaluate", "terrain-real-data", str(bad), "--profile", str(tmp_path / "x.npz")])
    assert result.exit_code == 2
    ragged = tmp_path / "ragged.csv"
    ragged.write_text("a,b\n1,2\n3\n")
    result = runner.invoke(app, ["evaluate", "terrain-real-data", str(ragged), "--profile", str(ragged)])
    assert result.exit_code == 2 and "Traceback" not in result.output


@pytest.mark.slow(seconds=15)  # a model fit: the paper's GP (trained once a run, ~12 CPU s, by the first to ask)
def test_real_jackal_windows_pick_the_true_ground_above_chance(
    jackal: Path, paper_model_file: Path, tmp_path: Path
) -> None:
    out = tmp_path / "r.json"
    result = runner.invoke(app, ["evaluate", "terrain-real-data", str(jackal / "gp_test.csv"), "--profile",
                                 str(paper_model_file), "--window", "30", "-n", "30", "--json", "-o", str(out)])
    assert result.exit_code == 0, result.output
    scores = json.loads(out.read_text())["windows"]["30"]
    assert set(scores) == {"asphalt", "grass", "tile"}
    for ground, s in scores.items():  # three grounds: chance is 1/3
        assert s["top_fraction"] > 0.5, (ground, s)
