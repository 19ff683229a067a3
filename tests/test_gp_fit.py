"""The hyperparameter fit generalises: it resists overfitting few noisy points, matches the paper's own fit on the
paper's Jackal data (skips without it), and `gpmppi train` warns when a GP is worse than the nominal model."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpmppi.gp.fit import (
    Hyperparameters,
    clip_outliers,
    fit_hyperparameters,
    nn_noise_variance,
    one_torch_thread,
)
from gpmppi.gp.model_file import GPModel
from gpmppi.gp.train import Transitions, factorize, train_model
from services.planner import log_model_fit
from tools.cli import app

runner = CliRunner()
LO, HI = np.array([0.0, -1.5, 0.0, -1.5]), np.array([2.0, 1.5, 2.0, 1.5])


def _signal(x: np.ndarray) -> np.ndarray:
    return 0.01 * np.sin(2.0 * x[:, 0]) * np.cos(x[:, 3])


def _predict(x: np.ndarray, y: np.ndarray, hp: Hyperparameters, xq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predictive mean and variance (noise included) per task at xq."""
    chol, alpha = factorize(x, y, hp)
    means, variances = [], []
    for t in range(len(y)):
        z, zq = x / hp.lengthscale[t], xq / hp.lengthscale[t]
        k = hp.outputscale[t] * np.exp(-0.5 * ((zq[:, None] - z[None]) ** 2).sum(-1))
        v = np.linalg.solve(chol[t], k.T)
        means.append(k @ alpha[t])
        variances.append(hp.outputscale[t] - (v**2).sum(0) + hp.noise[t])
    return np.stack(means), np.stack(variances)


def _plain_mll_fit(x: np.ndarray, y: np.ndarray, iters: int = 300) -> Hyperparameters:
    """Plain maximum marginal likelihood (no floor, prior, restarts or early stopping): what overfits."""
    import gpytorch
    import torch

    torch.manual_seed(0)
    t = len(y)
    batch = torch.Size([t])
    xt = torch.as_tensor(x).expand(t, *x.shape).contiguous()
    scale = np.sqrt((y**2).mean(1))
    yt = torch.as_tensor(y / scale[:, None])

    class GP(gpytorch.models.ExactGP):
        def __init__(self) -> None:
            super().__init__(xt, yt, gpytorch.likelihoods.GaussianLikelihood(
                batch_shape=batch, noise_constraint=gpytorch.constraints.GreaterThan(1e-6)))
            self.mean_module = gpytorch.means.ZeroMean(batch_shape=batch)
            self.covar_module = gpytorch.kernels.ScaleKernel(
                gpytorch.kernels.RBFKernel(ard_num_dims=4, batch_shape=batch), batch_shape=batch)

        def forward(self, a):
            return gpytorch.distributions.MultivariateNormal(self.mean_module(a), self.covar_module(a))

    m = GP().double()
    m.covar_module.base_kernel.lengthscale = torch.full((t, 1, 4), 0.3, dtype=torch.float64)
    m.likelihood.noise = torch.full((t, 1), 0.05, dtype=torch.float64)
    m.train()
    opt = torch.optim.Adam(m.parameters(), lr=0.05)
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(m.likelihood, m)
    with one_torch_thread():  # as `fit_hyperparameters` fits
        for _ in range(iters):
            opt.zero_grad()
            (-mll(m(xt), yt)).sum().backward()
            opt.step()
    return Hyperparameters(m.covar_module.base_kernel.lengthscale.detach().numpy().reshape(t, 4).copy(),
                           m.covar_module.outputscale.detach().numpy() * scale**2,
                           m.likelihood.noise.detach().numpy().reshape(t) * scale**2)


@pytest.mark.slow(seconds=10)  # two hyperparameter fits and a model's training
def test_fit_resists_overfitting_few_noisy_points() -> None:
    """40 points whose noise (sd 0.03) dwarfs the signal (amplitude 0.01; none at all on the second task). Plain
    maximum likelihood explains the noise as signal (noise variance collapses to a few % of the truth); the fit keeps
    the noise near the truth and predicts fresh data far more honestly (NLL). It cannot make 40 such points useful:
    its mean is still a little worse than no GP, and the fit report flags exactly that."""
    rng = np.random.default_rng(3)
    x = rng.uniform(LO, HI, (40, 4))
    y = np.stack([_signal(x) + rng.normal(0, 0.03, 40), rng.normal(0, 0.03, 40)])
    xq = rng.uniform(LO, HI, (2000, 4))
    yq = np.stack([_signal(xq) + rng.normal(0, 0.03, 2000), rng.normal(0, 0.03, 2000)])
    ours, diag = fit_hyperparameters(x, y, iters=200, seed=0)
    plain = _plain_mll_fit(x, y)
    assert np.all(plain.noise < 0.1 * 0.03**2), plain.noise  # the overfit this guards against does happen
    assert np.all(ours.noise >= 0.5 * 0.03**2), ours.noise
    assert np.all(ours.noise >= diag.noise_floor * (1 - 1e-9))
    rmse_nominal = np.sqrt((yq**2).mean(1))
    nll = {}
    for name, hp in (("ours", ours), ("plain", plain)):
        mean, var = _predict(x, y, hp, xq)
        nll[name] = (0.5 * np.log(2 * np.pi * var) + 0.5 * (yq - mean) ** 2 / var).mean(1)
        if name == "ours":
            rmse = np.sqrt(((yq - mean) ** 2).mean(1))
            assert np.all(rmse <= 1.1 * rmse_nominal), (rmse, rmse_nominal)
    assert np.all(nll["ours"] < nll["plain"] - 0.1), nll
    # the warning: a test set from the same distribution shows the GP does not help
    sets = {"sand": Transitions(x, y.T)}
    _, report = train_model(sets, np.array([0.2, 0.3, 0.05, 1.0, 0.15, 1.05]), {"sand": np.ones(5)}, points=40,
                            seed=0, test_sets={"sand": Transitions(xq, yq.T)})
    worse = report.gp_worse_than_nominal()
    assert worse and all(w["rmse_gp"] > w["rmse_nominal"] for w in worse)


def test_noise_floor_estimate_and_outlier_clipping() -> None:
    rng = np.random.default_rng(0)
    x = rng.uniform(LO, HI, (2000, 4))
    y = np.stack([0.1 * x[:, 0] + rng.normal(0, 0.02, 2000)])
    # nearest-neighbour differences recover the noise variance of a smooth signal (upward bias: the signal's change)
    assert 0.9 * 0.02**2 < nn_noise_variance(x, y)[0] < 1.3 * 0.02**2
    spiky = y.copy()
    spiky[0, :5] = 5.0
    clipped, n = clip_outliers(spiky)
    assert n == 5 and np.all(np.abs(clipped[0, :5]) < 1.0)
    np.testing.assert_array_equal(clipped[0, 5:], spiky[0, 5:])


def _write_csv(path: Path, x: np.ndarray, res: dict[str, np.ndarray]) -> Path:
    cols = ["cmd_lin", "cmd_ang", "curr_lin", "curr_ang"]
    data = [x]
    for t, r in res.items():
        cols += [f"{t}_Lin_Error", f"{t}_Ang_Error"]
        data.append(r)
    np.savetxt(path, np.column_stack(data), delimiter=",", header=",".join(cols), comments="")
    return path


@pytest.fixture
def theta_file(tmp_path: Path) -> Path:
    p = tmp_path / "theta.json"
    p.write_text('{"theta": [0.2, 0.3, 0.05, 1.0, 0.15, 1.05]}')
    return p


def test_warning_when_the_gp_is_worse_than_nominal(tmp_path: Path, theta_file: Path, caplog) -> None:
    """A residual that reverses between training and test (the terrain changed) cannot be fitted away: train warns
    naming the task and both RMSEs, the model file records it, and the planner's start-up log repeats it."""
    rng = np.random.default_rng(1)
    x, xt = rng.uniform(LO, HI, (120, 4)), rng.uniform(LO, HI, (120, 4))

    def res(a: np.ndarray, sign: float) -> np.ndarray:
        return np.column_stack([sign * 0.05 * np.sin(2 * a[:, 0]), 0.03 * a[:, 1]]) + rng.normal(0, 0.002, (len(a), 2))

    train = _write_csv(tmp_path / "train.csv", x, {"Sand": res(x, 1.0)})
    test = _write_csv(tmp_path / "test.csv", xt, {"Sand": res(xt, -1.0)})
    out = tmp_path / "m.npz"
    result = runner.invoke(app, ["train", str(train), "--theta", str(theta_file), "--test-data", str(test),
                                 "--iters", "60", "--grid-nodes", "0", "-o", str(out)])
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    model = GPModel.load(out)
    worse = model.fit_report["gp_worse_than_nominal"]
    assert [(w["terrain"], w["output"]) for w in worse] == [("sand", "v")]
    w = worse[0]
    assert w["rmse_gp"] > w["rmse_nominal"] and w["eval_set"] == "test data"
    assert "warning: GP for sand v is worse than the nominal model on test data" in text
    assert f"RMSE {w['rmse_gp']:.4f} with the GP vs {w['rmse_nominal']:.4f} without" in text
    assert "sand omega" not in text  # omega's residual did not change: no warning for it
    with caplog.at_level(logging.WARNING):
        assert log_model_fit(logging.getLogger("planner-test"), model, str(out)) == 1
    assert "sand v is worse than the nominal model" in caplog.text and str(out) in caplog.text


def test_csv_holds_data_out_by_default(tmp_path: Path, theta_file: Path) -> None:
    rng = np.random.default_rng(2)
    x = rng.uniform(LO, HI, (100, 4))
    train = _write_csv(tmp_path / "train.csv", x, {"Tile": np.column_stack([_signal(x), 0 * _signal(x)])
                                                   + rng.normal(0, 0.002, (100, 2))})
    out = tmp_path / "m.npz"
    result = runner.invoke(app, ["train", str(train), "--theta", str(theta_file), "--iters", "30",
                                 "--min-coverage", "0", "--grid-nodes", "0", "-o", str(out)])
    assert result.exit_code == 0, result.output
    fit = GPModel.load(out).fit_report
    assert fit["held_out"] and fit["eval_set"] == "held-out 20%" and fit["hyperparameters"] == "fitted"
    assert 10 <= fit["tasks"][0]["steps"] <= 30


# ---- the paper's Jackal data -----------------------------------------------------------------------------------
# test-set figures of the paper's own hyperparameters on the same inputs (issue table: RMSE with the GP, NLL)
PAPER = {("asphalt", "v"): (0.0169, -2.35), ("asphalt", "omega"): (0.0082, -3.01),
         ("grass", "v"): (0.0307, -1.90), ("grass", "omega"): (0.0100, -3.06),
         ("tile", "v"): (0.0221, -2.29), ("tile", "omega"): (0.0092, -3.08)}


# the held-out splits fitted: seed 0 by default (~30 s of CPU a seed, the suite's largest single cost after the
# determinism test); `GPMPPI_PAPER_FIT_SEEDS=0,1,2` fits those, side by side (docs/development.md)
PAPER_SEEDS = tuple(int(s) for s in os.environ.get("GPMPPI_PAPER_FIT_SEEDS", "0").split(","))


def _paper_fit(jackal: Path, seed: int):
    """The fit report of `gpmppi train`'s fit on the paper's training data (held-out split by `seed`), scored on
    the paper's test set."""
    from tools.train import build_training_sets
    from tools.train_data import csv_inputs, csv_residuals, read_csv_columns

    sets, theta, edd5, _, _ = build_training_sets(jackal / "gp_train.csv", None, jackal / "theta.json",
                                            jackal / "edd5.json", 0.1, None, seed)
    cols = read_csv_columns(jackal / "gp_test.csv")
    tx, tres = csv_inputs(cols, jackal / "gp_test.csv"), csv_residuals(cols, jackal / "gp_test.csv")
    _, report = train_model(sets, theta, edd5, seed=seed, test_sets={t: Transitions(tx, tres[t]) for t in sets})
    return report


def _one_torch_thread() -> None:
    import torch

    torch.set_num_threads(1)


@pytest.mark.slow(seconds=27)
def test_paper_data_fit_matches_the_papers_own(jackal: Path) -> None:
    """Each seed's fit (its own held-out split) on the paper's test set: no worse than nominal, RMSE within 5% of
    the paper's, NLL within 0.1 of it. Several seeds' fits run side by side, a spawned process each (each is mostly
    serial Python and torch work on one core); one test for them all, so that the parallel workers cannot split
    them up."""
    if len(PAPER_SEEDS) == 1:
        reports = {PAPER_SEEDS[0]: _paper_fit(jackal, PAPER_SEEDS[0])}
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        # one torch thread each: the processes share the cores, and idle intra-op threads only contend for them
        with ProcessPoolExecutor(len(PAPER_SEEDS), mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_one_torch_thread) as pool:
            futures = {seed: pool.submit(_paper_fit, jackal, seed) for seed in PAPER_SEEDS}
            reports = {seed: f.result() for seed, f in futures.items()}
    for seed, report in reports.items():
        assert report.held_out and not report.gp_worse_than_nominal(), seed
        for f in report.terrains:
            for o, out in enumerate(("v", "omega")):
                rmse, nll = PAPER[(f.terrain, out)]
                where = (seed, f.terrain, out, f.rmse_nominal[o], f.rmse_gp[o], f.nll[o])
                assert f.rmse_gp[o] <= f.rmse_nominal[o], where
                assert f.rmse_gp[o] <= 1.05 * rmse, where
                assert f.nll[o] <= nll + 0.1, where


@pytest.mark.parametrize(
    ("test_terrains", "message"),
    [(["Tile"], "no residual columns for ['sand']"),
     (["Sand", "Tile"], "terrains ['tile'] were not trained")],
)
def test_test_file_with_other_terrains_is_refused(tmp_path: Path, theta_file: Path, test_terrains: list[str],
                                                   message: str) -> None:
    rng = np.random.default_rng(4)
    x = rng.uniform(LO, HI, (30, 4))
    train = _write_csv(tmp_path / "train.csv", x, {"Sand": rng.normal(0, 0.01, (30, 2))})
    test = _write_csv(tmp_path / "test.csv", x, {t: rng.normal(0, 0.01, (30, 2)) for t in test_terrains})
    out = tmp_path / "m.npz"
    result = runner.invoke(app, ["train", str(train), "--theta", str(theta_file), "--test-data", str(test),
                                 "--iters", "5", "-o", str(out)])
    text = " ".join(result.output.split())
    assert result.exit_code == 2 and message in text and "test.csv" in text, result.output
    assert not out.exists()


def test_test_file_missing_an_input_column_is_refused(tmp_path: Path, theta_file: Path) -> None:
    rng = np.random.default_rng(5)
    x = rng.uniform(LO, HI, (30, 4))
    train = _write_csv(tmp_path / "train.csv", x, {"Sand": rng.normal(0, 0.01, (30, 2))})
    test = tmp_path / "test.csv"
    np.savetxt(test, np.column_stack([x[:, :3], rng.normal(0, 0.01, (30, 2))]), delimiter=",", comments="",
               header="cmd_lin,cmd_ang,curr_lin,Sand_Lin_Error,Sand_Ang_Error")
    result = runner.invoke(app, ["train", str(train), "--theta", str(theta_file), "--test-data", str(test),
                                 "-o", str(tmp_path / "m.npz")])
    assert result.exit_code == 2 and "missing input column 'curr_ang'" in " ".join(result.output.split())
