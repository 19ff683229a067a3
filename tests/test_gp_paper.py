"""The trainer and `gp predict` against GPyTorch on the paper's Jackal data (skips without it)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpmppi.gp.fit import one_torch_thread
from tools.cli import app

runner = CliRunner()


def _read(path: Path) -> tuple[list[str], np.ndarray]:
    header = path.read_text().splitlines()[0].split(",")
    return header, np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def _gpytorch_reference(train_x, train_y, hp: dict, test_x) -> tuple[np.ndarray, np.ndarray]:
    """Predictive mean and latent variance of a GPyTorch batch ExactGP with the given hyperparameters."""
    import gpytorch
    import torch

    t = train_y.shape[0]
    batch = torch.Size([t])
    x_t = torch.as_tensor(train_x).expand(t, *train_x.shape).contiguous()
    y_t = torch.as_tensor(train_y)

    class Batch(gpytorch.models.ExactGP):
        def __init__(self) -> None:
            super().__init__(x_t, y_t, gpytorch.likelihoods.GaussianLikelihood(batch_shape=batch))
            self.mean_module = gpytorch.means.ZeroMean(batch_shape=batch)
            self.covar_module = gpytorch.kernels.ScaleKernel(
                gpytorch.kernels.RBFKernel(ard_num_dims=4, batch_shape=batch), batch_shape=batch
            )

        def forward(self, x):
            return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))

    m = Batch().double()
    m.covar_module.base_kernel.lengthscale = torch.as_tensor(hp["lengthscale"]).reshape(t, 1, 4)
    m.covar_module.outputscale = torch.as_tensor(hp["outputscale"])
    noise = np.asarray(hp["task_noise"]) + hp["shared_noise"]
    m.likelihood.noise = torch.as_tensor(noise).reshape(t, 1)
    m.eval()
    means, variances = [], []
    with torch.no_grad(), gpytorch.settings.fast_pred_var(False), one_torch_thread():
        for start in range(0, len(test_x), 100):  # chunks: large batched predictions are memory hungry
            xc = torch.as_tensor(test_x[start : start + 100]).expand(t, -1, 4).contiguous()
            f = m(xc)
            means.append(f.mean.numpy().T)
            variances.append(f.variance.numpy().T)
    return np.concatenate(means), np.concatenate(variances)


@pytest.fixture(scope="module")
def paper_model(paper_model_file: Path) -> Path:
    """`gpmppi train` on the paper's data (conftest's session fixture: trained once for this and the grid test)."""
    return paper_model_file


@pytest.mark.slow(seconds=2)  # a model fit: the paper's GP (trained once a run, ~12 CPU s, by the first to ask)
def test_exact_predict_matches_gpytorch(jackal: Path, paper_model: Path, tmp_path: Path) -> None:
    pred = tmp_path / "pred.csv"
    result = runner.invoke(app, ["gp", "predict", str(jackal / "gp_test.csv"), "--profile", str(paper_model),
                                 "-o", str(pred), "--mode", "exact"])
    assert result.exit_code == 0, result.output
    header, ours = _read(pred)
    train_header, train = _read(jackal / "gp_train.csv")
    _, test = _read(jackal / "gp_test.csv")
    hp = json.loads((jackal / "gp_hyperparameters.json").read_text())
    # reference targets straight from the CSV, in the hyperparameter file's task order
    train_y = np.stack([train[:, train_header.index(f"{task}_Error")] for task in hp["tasks"]])
    ref_mean, ref_var = _gpytorch_reference(train[:, :4], train_y, hp, test[:, :4])
    np.testing.assert_array_equal(ours[:, :4], test[:, :4])
    for k, task in enumerate(hp["tasks"]):
        mean = ours[:, header.index(f"{_ours(task)}_mean")]
        var = ours[:, header.index(f"{_ours(task)}_var")]
        assert np.max(np.abs(mean - ref_mean[:, k])) < 1e-4 * np.max(np.abs(ref_mean[:, k])), task
        np.testing.assert_allclose(var, ref_var[:, k], rtol=1e-4, err_msg=task)


def _ours(task: str) -> str:
    """Our task name for a paper task name: terrain lower case, output kept (asphalt_Lin)."""
    terrain, out = task.split("_")
    return f"{terrain.lower()}_{out}"


@pytest.mark.slow(seconds=2)  # a model fit: the paper's GP (trained once a run, ~12 CPU s, by the first to ask)
def test_gp_beats_nominal_on_paper_test_set(jackal: Path, paper_model: Path, tmp_path: Path) -> None:
    header, test = _read(jackal / "gp_test.csv")
    for mode in ("exact", "grid"):
        pred = tmp_path / f"{mode}.csv"
        assert runner.invoke(app, ["gp", "predict", str(jackal / "gp_test.csv"), "--profile", str(paper_model),
                                   "-o", str(pred), "--mode", mode]).exit_code == 0
        pheader, ours = _read(pred)
        for terrain in ("Asphalt", "Grass", "Tile"):
            for out in ("Lin", "Ang"):
                target = test[:, header.index(f"{terrain}_{out}_Error")]
                mean = ours[:, pheader.index(f"{terrain.lower()}_{out}_mean")]
                rmse_nominal = np.sqrt(np.mean(target**2))  # the targets are residuals of the nominal model
                rmse_gp = np.sqrt(np.mean((target - mean) ** 2))
                assert rmse_gp < rmse_nominal, (mode, terrain, out, rmse_gp, rmse_nominal)
