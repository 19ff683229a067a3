"""The fit's choice among its restarts and steps (`gpmppi.gp.fit`, `selection`): with one seeded validation fold
("fold") the chosen hyperparameters move with the fit's seed; chosen by leave-one-out on all the inputs ("loo") they
do not. The closed-form leave-one-out density is what refitting without each point gives, and `gpmppi train
--fit` reaches the fit and is named in the profile's `made_by`."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpmppi.gp.fit import _loo_score, fit_hyperparameters
from gpmppi.gp.model_file import GPModel
from tools.cli import app

LO, HI = np.array([0.0, -1.5, 0.0, -1.5]), np.array([2.0, 1.5, 2.0, 1.5])


def _data(n: int = 80) -> tuple[np.ndarray, np.ndarray]:
    """Two tasks with structure on some inputs and noise about a tenth to a third of the signal."""
    rng = np.random.default_rng(3)
    x = rng.uniform(LO, HI, (n, 4))
    y = np.stack([0.01 * np.sin(2 * x[:, 0]) * np.cos(x[:, 3]) + rng.normal(0, 0.003, n),
                  0.02 * np.cos(x[:, 1]) + rng.normal(0, 0.005, n)])
    return x, y


# the inputs each task's signal depends on: the lengthscales that shape its predictions
RELEVANT = ((0, 0), (0, 3), (1, 1))


@pytest.mark.slow(seconds=12)  # five fits of 80 points x 2 tasks, 100 steps each (and torch's first fit in a process)
def test_the_loo_choice_does_not_hinge_on_the_seed_the_fold_choice_does() -> None:
    x, y = _data()
    fold = [fit_hyperparameters(x, y, iters=100, seed=s, selection="fold")[0] for s in (0, 1)]
    loo = [fit_hyperparameters(x, y, iters=100, seed=s, selection="loo")[0] for s in (0, 1, 2)]
    # the fold's seed moves a lengthscale that matters by more than a quarter: the draw the loo choice removes
    moved = max(abs(math.log(fold[0].lengthscale[i] / fold[1].lengthscale[i])) for i in RELEVANT)
    assert moved > math.log(1.25), [(fold[0].lengthscale[i], fold[1].lengthscale[i]) for i in RELEVANT]
    for other in loo[1:]:
        for name in ("lengthscale", "outputscale", "noise"):
            np.testing.assert_allclose(getattr(other, name), getattr(loo[0], name), rtol=0.02, err_msg=name)


def test_closed_form_loo_density_is_refitting_without_each_point() -> None:
    import torch

    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, (15, 4))
    y = np.stack([np.sin(3 * x[:, 0]) + rng.normal(0, 0.1, 15), x[:, 1] + rng.normal(0, 0.2, 15)])
    ls = np.array([[0.3, 0.5, 1.0, 2.0], [0.7, 0.4, 0.9, 1.1]])
    os_, nz = np.array([1.2, 0.5]), np.array([0.01, 0.04])
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    fast = _loo_score(t(x), t(y), t(ls), t(os_), t(nz), restarts=1)
    for task in range(2):
        nll = []
        for i in range(15):
            keep = np.arange(15) != i
            z, zi = x[keep] / ls[task], x[i] / ls[task]
            k = os_[task] * np.exp(-0.5 * ((z[:, None] - z[None]) ** 2).sum(-1)) + nz[task] * np.eye(14)
            ki = os_[task] * np.exp(-0.5 * ((z - zi) ** 2).sum(-1))
            mean = ki @ np.linalg.solve(k, y[task, keep])
            var = os_[task] - ki @ np.linalg.solve(k, ki) + nz[task]
            nll.append(0.5 * np.log(2 * np.pi * var) + 0.5 * (y[task, i] - mean) ** 2 / var)
        assert fast[task] == pytest.approx(np.mean(nll), rel=1e-9)


def test_an_unknown_selection_is_refused() -> None:
    x, y = _data(20)
    with pytest.raises(ValueError, match="selection must be one of"):
        fit_hyperparameters(x, y, iters=1, seed=0, selection="best")


@pytest.mark.parametrize("fit", ["stable", "seeded"])
def test_train_takes_the_fit_and_names_it(tmp_path: Path, fit: str) -> None:
    rng = np.random.default_rng(2)
    x = rng.uniform(LO, HI, (100, 4))
    res = np.column_stack([0.01 * np.sin(2 * x[:, 0]), 0.02 * x[:, 1]]) + rng.normal(0, 0.002, (100, 2))
    csv = tmp_path / "train.csv"
    np.savetxt(csv, np.column_stack([x, res]), delimiter=",", comments="",
               header="cmd_lin,cmd_ang,curr_lin,curr_ang,Tile_Lin_Error,Tile_Ang_Error")
    theta = tmp_path / "theta.json"
    theta.write_text('{"theta": [0.2, 0.3, 0.05, 1.0, 0.15, 1.05]}')
    out = tmp_path / "m.npz"
    result = CliRunner().invoke(app, ["train", str(csv), "--theta", str(theta), "--iters", "20", "--min-coverage",
                                      "0", "--grid-nodes", "0", "--fit", fit, "-o", str(out)])
    assert result.exit_code == 0, result.output
    made_by = GPModel.load(out).made_by
    assert made_by is not None and made_by.endswith(f"--fit {fit}")


@pytest.mark.slow(seconds=2)  # four trainings of 60 inputs x 2 tasks
def test_the_stable_fit_draws_nothing_from_the_seed_but_the_held_out_split() -> None:
    """Without a held-out split, `train_model(fit="stable")` makes the same GP whatever the seed: its k-means of the
    inputs, its restarts and its choice do not draw from it; the seeded fit's inputs and hyperparameters move."""
    from gpmppi.gp.train import Transitions, train_model

    rng = np.random.default_rng(5)
    x = rng.uniform(LO, HI, (600, 4))
    res = np.column_stack([0.02 * np.sin(2 * x[:, 0]) * np.cos(x[:, 3]), 0.05 * np.cos(1.5 * x[:, 1]) * x[:, 2]])
    sets = {"sand": Transitions(x, res + rng.normal(0, [0.01, 0.02], (600, 2)))}
    theta, edd5 = np.array([0.2, 0.3, 0.05, 1.0, 0.15, 1.05]), {"sand": np.ones(5)}

    def model(fit: str, seed: int) -> GPModel:
        return train_model(sets, theta, edd5, points=60, iters=60, seed=seed, holdout=0.0, fit=fit)[0]

    stable, seeded = [model("stable", s) for s in (0, 1)], [model("seeded", s) for s in (0, 1)]
    assert not np.array_equal(seeded[0].train_x, seeded[1].train_x)
    assert not np.allclose(seeded[0].lengthscale, seeded[1].lengthscale, rtol=0.02)
    np.testing.assert_array_equal(stable[0].train_x, stable[1].train_x)
    for name in ("lengthscale", "outputscale", "noise", "alpha"):
        np.testing.assert_allclose(getattr(stable[1], name), getattr(stable[0], name), rtol=1e-9, err_msg=name)
    with pytest.raises(ValueError, match="fit must be one of"):
        train_model(sets, theta, edd5, points=60, iters=1, fit="lucky")
