"""`gpmppi gp predict` and `gpmppi bench gp` on a small model: outputs, and clear errors on bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_gp_model_file import small_model
from typer.testing import CliRunner

from gpmppi.gp.exact import ExactPredictor
from gpmppi.gp.grid import GridPredictor, build_grid
from tools.cli import app

runner = CliRunner()


@pytest.fixture(scope="module")
def model_path(tmp_path_factory) -> Path:
    m = small_model()
    m.set_grid(build_grid(m, 10))
    path = tmp_path_factory.mktemp("cli") / "m.npz"
    m.save(path)
    return path


def _inputs(path: Path, header: str, n: int = 25) -> tuple[Path, np.ndarray]:
    x = np.random.default_rng(4).uniform([0, -2, 0, -2], [2, 2, 2, 2], (n, 4))
    path.write_text(header + "\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in x) + "\n")
    return path, x


@pytest.mark.parametrize("header", ["cmd_lin,cmd_ang,curr_lin,curr_ang",
                                    "gp_ip_cmd_lin,gp_ip_cmd_ang,gp_ip_curr_lin,gp_ip_curr_ang"])
@pytest.mark.parametrize("mode", ["exact", "grid"])
def test_predict_writes_means_and_variances(model_path: Path, tmp_path: Path, header: str, mode: str) -> None:
    inputs, x = _inputs(tmp_path / "in.csv", header)
    out = tmp_path / "out.csv"
    result = runner.invoke(app, ["gp", "predict", str(inputs), "--profile", str(model_path),
                                 "-o", str(out), "--mode", mode])
    assert result.exit_code == 0, result.output
    cols = out.read_text().splitlines()[0].split(",")
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    from gpmppi.gp.model_file import GPModel

    model = GPModel.load(model_path)
    mean, var = (ExactPredictor(model) if mode == "exact" else GridPredictor(model)).predict(x)
    assert cols[:4] == ["cmd_lin", "cmd_ang", "curr_lin", "curr_ang"]
    np.testing.assert_allclose(data[:, :4], x)
    for t, name in enumerate(model.tasks):
        np.testing.assert_allclose(data[:, cols.index(f"{name}_mean")], mean[:, t], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(data[:, cols.index(f"{name}_var")], var[:, t], rtol=1e-12, atol=1e-15)


def test_predict_errors(model_path: Path, tmp_path: Path) -> None:
    out = tmp_path / "out.csv"
    bad, _ = _inputs(tmp_path / "bad.csv", "cmd_lin,cmd_ang,curr_lin,speed")
    result = runner.invoke(app, ["gp", "predict", str(bad), "--profile", str(model_path),
                                 "-o", str(out)])
    assert result.exit_code == 2 and "missing input column 'curr_ang'" in result.output and not out.exists()
    good, _ = _inputs(tmp_path / "good.csv", "cmd_lin,cmd_ang,curr_lin,curr_ang")
    result = runner.invoke(app, ["gp", "predict", str(good), "--profile", str(model_path),
                                 "-o", str(out), "--mode", "fast"])
    assert result.exit_code == 2 and "--mode" in result.output and not out.exists()
    result = runner.invoke(app, ["gp", "predict", str(good), "--profile", str(good),
                                 "-o", str(out)])
    assert result.exit_code == 2 and "not a GP model file" in result.output and not out.exists()


def test_bench_reports_accuracy_and_rates(model_path: Path) -> None:
    result = runner.invoke(app, ["bench", "gp", "--profile", str(model_path), "--points", "3000", "--json"])
    assert result.exit_code == 0, result.output
    r = json.loads(result.output)
    assert r["grid_nodes"] == 10 and len(r["tasks"]) == 4
    for t in r["tasks"]:
        assert 0 < t["mean_error_pct"] < 10 and 0 < t["var_error_pct"] < 20
    assert r["exact_per_s"] > 0 and r["grid_per_s"] > r["exact_per_s"]
