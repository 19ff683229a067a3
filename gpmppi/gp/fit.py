"""Fitting the GP batch's hyperparameters so that the fit generalises (GPyTorch, float64, seeded).

Maximum marginal likelihood alone overfits small, noisy, heavy-tailed real data: it drives the
noise towards zero and the lengthscales below the spacing of the data, so the GP interpolates
individual measurements (outliers included) and predicts worse than no GP on new data (the paper's
Jackal data: asphalt v went from RMSE 0.0194 without a GP to 0.0281 with one). The fit guards
against that as follows; choices among fits are made on held-out data, never on training likelihood.

- **Outlier clipping** (`clip_outliers`, applied by the caller to the targets it fits and conditions
  on): each task's targets are clipped to median +- `CLIP_MADS` robust standard deviations
  (1.4826 x median absolute deviation). Real odometry has isolated spikes that a Gaussian likelihood
  otherwise explains with short lengthscales.
- **Noise floor from the data.** Each task's noise variance is constrained (GPyTorch `GreaterThan`) to
  at least `NOISE_FLOOR_FRACTION` x the nearest-neighbour difference estimate of the measurement noise,
  sigma^2 ~ 1/(2n) sum_i (y_i - y_nn(i))^2 over nearest neighbours in standardized input space
  (Devroye et al., "Nearest neighbor-based estimation of the residual variance", 2018). The estimate
  includes the signal's change between neighbours, so it errs on the side of more noise; on the
  paper's data most tasks' fitted noise sits at this floor, so it does most of the regularising.
- **Priors** (maximum a posteriori, GPyTorch priors): on inputs scaled to the unit cube the
  lengthscales get the dimension-scaled LogNormal(sqrt(2) + ln(d)/2, sqrt(3)) of Hvarfner et al.,
  "Vanilla Bayesian optimization performs great in high dimensions" (2024); the output scale (targets
  scaled to unit RMS) a LogNormal(0, 1); lengthscales are constrained to at least `MIN_LENGTHSCALE` of
  the input range.
- **Restarts**: `restarts` initialisations (the first at half the input range and noise `NOISE_INIT`,
  the rest seeded log-uniform), fitted as one GPyTorch batch.
- **Early stopping on a validation split**: one seeded fold of `folds` (20 % for 5) is held out of the
  likelihood; every `CHECK_EVERY` Adam steps each (restart, task)'s mean predictive negative log
  density on it, conditioned on the rest, is measured, and each task keeps the hyperparameters of its
  best (step, restart). `USED_FOLDS` > 1 scores more folds (K-fold cross-validation, the choice then
  being the geometric mean over folds) at proportionally more time. The caller conditions the final
  model on all its training inputs.
- **Or early stopping on leave-one-out** (`selection="loo"`, `gpmppi train --fit stable`): no fold is held out of the
  likelihood; each (restart, task)'s score is the mean leave-one-out predictive negative log density on all the
  inputs, in closed form (`_loo_score`), and the restarts start from one fixed set whatever the seed, so the choice
  draws nothing from it. Measured on the Jackal (docs/training.md, "A fit that does not hinge on its seed?"): it
  removes the seed's fold and restarts but not the result's spread, which follows the data (the 300 inputs and the
  held-out rows).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from sklearn.neighbors import NearestNeighbors

if TYPE_CHECKING:
    from torch import Tensor

NOISE_FLOOR_FRACTION = 1.0
MIN_LENGTHSCALE = 0.05  # of each input's range
RESTARTS = 4
FOLDS = 5  # the validation split is one fold of FOLDS (20 %)
USED_FOLDS = 1  # folds scored (each adds a batch of restarts x tasks GPs: time grows with it)
CLIP_MADS = 5.0
CHECK_EVERY = 5
NOISE_INIT = 0.1
LOO_INIT_SEED = 0  # "loo": the restarts' initialisations, one fixed set whatever the fit's seed
SELECTIONS = ("fold", "loo")  # how the (step, restart) is chosen: one seeded validation fold, or leave-one-out


@dataclass
class Hyperparameters:
    """Per-task kernel hyperparameters in model task order."""

    lengthscale: np.ndarray  # (T, 4)
    outputscale: np.ndarray  # (T,)
    noise: np.ndarray  # (T,)


@dataclass
class FitDiagnostics:
    """What the fit chose, per task: the validation NLL (targets scaled to unit RMS), the step and restart."""

    val_nll: np.ndarray  # (T,)
    best_iter: np.ndarray  # (T,)
    best_restart: np.ndarray  # (T,)
    noise_floor: np.ndarray  # (T,) in target units squared
    final_loss: float  # mean negative log posterior per point of the chosen (restart, step), averaged over tasks
    folds: int  # cross-validation folds the choice was made on (1: none, too few points)


def clip_outliers(y: np.ndarray, mads: float = CLIP_MADS) -> tuple[np.ndarray, int]:
    """Clip each row of y (T, n) to median +- mads x its robust standard deviation (1.4826 MAD); (clipped, count)."""
    med = np.median(y, axis=1, keepdims=True)
    sd = 1.4826 * np.median(np.abs(y - med), axis=1, keepdims=True)
    out = np.clip(y, med - mads * sd, med + mads * sd)
    return out, int(np.count_nonzero(out != y))


def nn_noise_variance(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Nearest-neighbour difference estimate of the noise variance of each row of y (T, n) at inputs x (n, 4)."""
    n = len(x)
    if n < 2:
        return np.zeros(y.shape[0])
    z = x / (x.std(0) + 1e-9)
    nb = NearestNeighbors(n_neighbors=2).fit(z).kneighbors(z, return_distance=False)
    # the first neighbour is the point itself unless duplicates tie: take the first index that is not i
    j = np.where(nb[:, 0] == np.arange(n), nb[:, 1], nb[:, 0])
    return 0.5 * np.mean((y - y[:, j]) ** 2, axis=1)


def cv_folds(n: int, folds: int, seed: int, used: int | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Seeded K-fold (fit indices, validation indices) with equal-size fit sets (batched fitting needs them:
    a fold whose complement is larger drops its surplus at random); [(all, none)] when too few points."""
    if folds < 2 or n < 2 * folds:
        return [(np.arange(n), np.arange(0))]
    rng = np.random.default_rng(seed + 7919)
    parts = np.array_split(rng.permutation(n), folds)
    m = n - max(len(p) for p in parts)
    out = []
    for k, val in enumerate(parts):
        rest = np.concatenate([p for j, p in enumerate(parts) if j != k])
        out.append((np.sort(rng.choice(rest, m, replace=False) if len(rest) > m else rest), np.sort(val)))
    return out[:used]


def fit_hyperparameters(
    train_x: np.ndarray, train_y: np.ndarray, iters: int, seed: int, lr: float = 0.05,
    restarts: int | None = None, folds: int | None = None, selection: str = "fold",
) -> tuple[Hyperparameters, FitDiagnostics]:
    """Fit each task's hyperparameters (see the module docstring); train_y is (T, n) at shared inputs (n, 4)."""
    import gpytorch
    import torch

    restarts = RESTARTS if restarts is None else restarts
    folds = FOLDS if folds is None else folds
    if selection not in SELECTIONS:
        raise ValueError(f"selection must be one of {SELECTIONS}, got {selection!r}")
    if restarts < 1:
        raise ValueError(f"restarts must be at least 1, got {restarts}")
    if iters < 1:
        raise ValueError(f"iters must be at least 1, got {iters}")
    torch.manual_seed(seed)
    with one_torch_thread():
        return _fit(gpytorch, torch, train_x, train_y, iters, seed, lr, restarts, folds, selection)


@contextlib.contextmanager
def one_torch_thread() -> Iterator[None]:
    """torch's intra-op threads at 1 inside the block, as they were after it. On these GPs' small batched matrices a
    second thread only waits (the fit measured ~2.5x faster on one; beside other work, as in the test suite, the plain
    likelihood fit of tests/test_gp_fit.py 0.54-0.64 CPU s on one thread against 4.1-7.6 on two)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _fit(gpytorch, torch, train_x: np.ndarray, train_y: np.ndarray, iters: int, seed: int, lr: float,
         restarts: int, folds: int, selection: str) -> tuple[Hyperparameters, FitDiagnostics]:
    n_tasks, d = train_y.shape[0], train_x.shape[1]
    y_scale = np.maximum(np.sqrt((train_y**2).mean(1)), 1e-9)  # zero-mean GP: scale by RMS, not std
    y_n = train_y / y_scale[:, None]
    lo, span = train_x.min(0), np.maximum(np.ptp(train_x, axis=0), 1e-3)
    x_u = (train_x - lo) / span  # unit cube: the lengthscale prior's reference scale
    floor = np.maximum(NOISE_FLOOR_FRACTION * nn_noise_variance(x_u, y_n), 1e-6)
    loo = selection == "loo" and len(train_x) >= 2
    splits = [(np.arange(len(train_x)), np.arange(0))] if loo else cv_folds(len(train_x), folds, seed, USED_FOLDS)
    k_f, rt = len(splits), restarts * n_tasks
    b = k_f * rt  # batch: fold-major, then restart, then task
    batch = torch.Size([b])
    dt = torch.float64
    x_fit = torch.as_tensor(np.repeat(np.stack([x_u[f] for f, _ in splits]), rt, axis=0), dtype=dt)
    y_fit = torch.as_tensor(np.concatenate([np.tile(y_n[:, f], (restarts, 1)) for f, _ in splits]), dtype=dt)
    floor_b = torch.as_tensor(np.tile(floor, k_f * restarts).reshape(b, 1), dtype=dt)

    class BatchGP(gpytorch.models.ExactGP):
        def __init__(self) -> None:
            lik = gpytorch.likelihoods.GaussianLikelihood(
                batch_shape=batch, noise_constraint=gpytorch.constraints.GreaterThan(floor_b)
            )
            super().__init__(x_fit, y_fit, lik)
            self.mean_module = gpytorch.means.ZeroMean(batch_shape=batch)
            ls_prior = gpytorch.priors.LogNormalPrior(math.sqrt(2.0) + 0.5 * math.log(d), math.sqrt(3.0))
            self.covar_module = gpytorch.kernels.ScaleKernel(
                gpytorch.kernels.RBFKernel(
                    ard_num_dims=d, batch_shape=batch, lengthscale_prior=ls_prior,
                    lengthscale_constraint=gpytorch.constraints.GreaterThan(MIN_LENGTHSCALE),
                ),
                batch_shape=batch, outputscale_prior=gpytorch.priors.LogNormalPrior(0.0, 1.0),
            )

        def forward(self, x: torch.Tensor) -> gpytorch.distributions.MultivariateNormal:
            return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))

    model = BatchGP().double()
    rng = np.random.default_rng(LOO_INIT_SEED if loo else seed)
    ls0 = np.empty((restarts, n_tasks, d))
    ls0[0] = 0.5  # half the input range: the data's spread
    ls0[1:] = np.exp(rng.uniform(math.log(0.1), math.log(3.0), (restarts - 1, n_tasks, d)))
    nz0 = np.empty((restarts, n_tasks))
    nz0[0] = NOISE_INIT
    nz0[1:] = np.exp(rng.uniform(math.log(0.02), math.log(1.0), (restarts - 1, n_tasks)))
    model.covar_module.base_kernel.lengthscale = torch.as_tensor(np.tile(ls0.reshape(rt, 1, d), (k_f, 1, 1)))
    model.covar_module.outputscale = torch.ones(b, dtype=dt)
    model.likelihood.noise = torch.maximum(torch.as_tensor(np.tile(nz0.reshape(rt, 1), (k_f, 1))), 1.01 * floor_b)
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(model.likelihood, model)

    x_t, y_t = torch.as_tensor(x_u, dtype=dt), torch.as_tensor(y_n, dtype=dt)
    steps, scores, params, losses = [], [], [], []
    for step in range(iters + 1):
        opt.zero_grad()
        per = -mll(model(x_fit), y_fit)  # (b,) negative log posterior per point
        if step % CHECK_EVERY == 0 or step == iters:
            with torch.no_grad():
                ls = model.covar_module.base_kernel.lengthscale.reshape(b, d).clone()
                os_ = model.covar_module.outputscale.reshape(b).clone()
                nz = model.likelihood.noise.reshape(b).clone()
                steps.append(step)
                losses.append(per.detach().numpy().copy())
                params.append(np.column_stack([ls.numpy(), os_.numpy(), nz.numpy()]))
                if loo:
                    scores.append(_loo_score(x_t, y_t, ls, os_, nz, restarts))
                else:
                    scores.append(_cv_score(x_t, y_t, splits, ls, os_, nz, restarts) if len(splits[0][1])
                                  else losses[-1])
        if step == iters:
            break
        per.sum().backward()
        opt.step()
    # per (check, restart, task): mean over folds; each task keeps its best (check, restart)
    sc = np.stack(scores).reshape(len(steps), k_f, restarts, n_tasks)
    sc = np.where(np.isfinite(sc), sc, np.inf).mean(1)
    flat = sc.reshape(-1, n_tasks)
    pick = np.argmin(flat, axis=0)
    c_i, r_i = np.divmod(pick, restarts)
    pr = np.stack(params).reshape(len(steps), k_f, restarts, n_tasks, d + 2)
    chosen = np.exp(np.log(pr[c_i, :, r_i, np.arange(n_tasks)]).mean(1))  # (T, d + 2): geometric mean over folds
    ls_ = np.stack(losses).reshape(len(steps), k_f, restarts, n_tasks)[c_i, :, r_i, np.arange(n_tasks)]
    hp = Hyperparameters(
        lengthscale=chosen[:, :d] * span,
        outputscale=chosen[:, d] * y_scale**2,
        noise=chosen[:, d + 1] * y_scale**2,
    )
    diag = FitDiagnostics(
        val_nll=flat[pick, np.arange(n_tasks)], best_iter=np.asarray(steps)[c_i], best_restart=r_i,
        noise_floor=floor * y_scale**2, final_loss=float(ls_.mean()), folds=k_f,
    )
    return hp, diag


def _cv_score(x: Tensor, y: Tensor, splits: list[tuple[np.ndarray, np.ndarray]],
              ls: Tensor, os_: Tensor, noise: Tensor, restarts: int) -> np.ndarray:
    """(b,) mean predictive negative log density of each fold's validation targets given its fit targets."""
    import torch

    rt = ls.shape[0] // len(splits)
    out = []
    for k, (fit_i, val_i) in enumerate(splits):
        s = slice(k * rt, (k + 1) * rt)
        yf = y[:, fit_i].repeat(restarts, 1)  # (rt, nf)
        yv = y[:, val_i].repeat(restarts, 1)
        zf = x[fit_i][None] / ls[s, None, :]  # (rt, nf, d)
        zv = x[val_i][None] / ls[s, None, :]
        kff = os_[s, None, None] * torch.exp(-0.5 * torch.cdist(zf, zf) ** 2)
        kff = kff + noise[s, None, None] * torch.eye(len(fit_i), dtype=x.dtype)
        kvf = os_[s, None, None] * torch.exp(-0.5 * torch.cdist(zv, zf) ** 2)
        chol, info = torch.linalg.cholesky_ex(kff)
        alpha = torch.cholesky_solve(yf[..., None], chol)[..., 0]
        mean = (kvf @ alpha[..., None])[..., 0]
        v = torch.linalg.solve_triangular(chol, kvf.transpose(1, 2), upper=False)
        var = torch.clamp(os_[s, None] - (v**2).sum(1) + noise[s, None], min=1e-12)
        nll = (0.5 * torch.log(2 * math.pi * var) + 0.5 * (yv - mean) ** 2 / var).mean(1)
        nll[info != 0] = float("inf")
        out.append(nll.numpy())
    return np.concatenate(out)


def _loo_score(x: Tensor, y: Tensor, ls: Tensor, os_: Tensor, noise: Tensor, restarts: int) -> np.ndarray:
    """(b,) mean leave-one-out predictive negative log density of each GP's own targets, in closed form (Rasmussen &
    Williams 2006, eq. 5.10-5.12): with K the kernel matrix plus noise and alpha = K^-1 y, point i's prediction from
    the others has mean y_i - alpha_i / [K^-1]_ii and variance 1 / [K^-1]_ii."""
    import torch

    z = x[None] / ls[:, None, :]  # (b, n, d)
    k = os_[:, None, None] * torch.exp(-0.5 * torch.cdist(z, z) ** 2)
    k = k + noise[:, None, None] * torch.eye(len(x), dtype=x.dtype)
    chol, info = torch.linalg.cholesky_ex(k)
    y_b = y.repeat(restarts, 1)  # (b, n): restart-major, then task, as the batch
    alpha = torch.cholesky_solve(y_b[..., None], chol)[..., 0]
    kinv_diag = torch.clamp(torch.diagonal(torch.cholesky_inverse(chol), dim1=1, dim2=2), min=1e-300)
    nll = (0.5 * torch.log(2 * math.pi / kinv_diag) + 0.5 * alpha**2 / kinv_diag).mean(1)
    nll[info != 0] = float("inf")
    return nll.numpy()
