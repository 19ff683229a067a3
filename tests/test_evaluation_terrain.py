"""The evaluation's terrain estimator: the configured method, the oracle, and bad settings from the CLI."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from typer.testing import CliRunner

from gpmppi.evaluation.runner import EvalSettings, OracleEstimator, make_terrain_estimator
from gpmppi.terrain.estimator import BayesTerrainEstimator
from gpmppi.terrain.least_squares import TerrainEstimator
from tools.cli import app

NAMES = ["asphalt", "grass", "tile"]


def test_the_evaluation_builds_the_configured_estimator() -> None:
    plant = SimpleNamespace(terrain="grass")
    assert isinstance(make_terrain_estimator(EvalSettings(), plant), BayesTerrainEstimator)
    paper = make_terrain_estimator(EvalSettings(terrain_estimator=(("method", "paper"), ("history", 30))), plant)
    assert isinstance(paper, TerrainEstimator) and paper.history == 30
    assert isinstance(make_terrain_estimator(EvalSettings(oracle_weights=True), plant), OracleEstimator)


def test_oracle_gives_the_terrain_under_the_plant_now() -> None:
    plant = SimpleNamespace(terrain="tile")
    oracle = OracleEstimator(plant, NAMES)
    oracle.observe(np.zeros(5), np.zeros(2), np.zeros(5))
    np.testing.assert_array_equal(oracle.estimate().weights, [0, 0, 1])
    plant.terrain = "grass"  # a --switch: the oracle follows at once
    np.testing.assert_array_equal(oracle.estimate().weights, [0, 1, 0])
    plant.terrain = "sand"  # no true weight on an unseen terrain
    np.testing.assert_allclose(oracle.estimate().weights, [1 / 3] * 3)


def test_cli_rejects_bad_estimator_settings_naming_them() -> None:
    for item, named in (("method=lstsq", "method"), ("switch_prob=2", "switch_prob"), ("windw=3", "windw")):
        res = CliRunner().invoke(app, ["evaluate", "tracking", "-m", "gp", "--estimator", item])
        assert res.exit_code == 2, res.output
        assert named in res.output and "--estimator" in res.output
