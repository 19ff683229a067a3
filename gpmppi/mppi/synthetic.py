"""A small synthetic GP model (seeded), for tests and benchmarks when no trained model is at hand.

Residuals of each terrain are smooth random functions (random Fourier features), distinct per
terrain so the terrain weights are identifiable; the GP is fitted on them with fixed
hyperparameters (exact Cholesky), and the grid table is built with the GP area's `build_grid`.
The numbers are made up: nothing here comes from a real robot.
"""

from __future__ import annotations

import numpy as np

from gpmppi.gp.grid import build_grid
from gpmppi.gp.model_file import GPModel, task_names
from gpmppi.terrain.settings import shipped_calibration

SYNTHETIC_THETA = np.array([0.2, 0.3, 0.05, 1.0, 0.15, 1.0])
SHIPPED_GROUNDS = ("tile", "asphalt", "grass")  # the grounds of the shipped calibration (gpmppi/data)
DOMAIN_LO = np.array([0.0, -np.pi, -0.5, -np.pi])
DOMAIN_HI = np.array([2.0, np.pi, 2.5, np.pi])


def residual_functions(n_tasks: int, seed: int, features: int = 12, amplitude: float = 0.06):
    """Per task a smooth function R^4 -> R (random Fourier features), returned as one callable (P,4)->(P,T)."""
    rng = np.random.default_rng(seed)
    scale = (DOMAIN_HI - DOMAIN_LO) / 2.0
    freq = rng.normal(size=(n_tasks, features, 4)) / scale
    phase = rng.uniform(0, 2 * np.pi, size=(n_tasks, features))
    amp = amplitude * rng.normal(size=(n_tasks, features)) / np.sqrt(features)

    def f(x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(x)
        arg = np.einsum("pd,tfd->ptf", x, freq) + phase[None]
        return (np.cos(arg) * amp[None]).sum(-1)

    return f


def synthetic_model(
    terrains: tuple[str, ...] = ("asphalt", "grass", "tile"), n_train: int = 120, nodes: int = 9, seed: int = 0
) -> GPModel:
    """Exact GPs fitted to seeded smooth residuals; the grid table has `nodes` per axis."""
    m = len(terrains)
    t = 2 * m
    rng = np.random.default_rng(seed)
    x = DOMAIN_LO + (DOMAIN_HI - DOMAIN_LO) * rng.uniform(size=(n_train, 4))
    y = residual_functions(t, seed + 1)(x)  # (n, T)
    lengthscale = np.tile((DOMAIN_HI - DOMAIN_LO) / 3.0, (t, 1))
    outputscale = np.full(t, 0.01)
    noise = np.full(t, 1e-4)
    chol = np.empty((t, n_train, n_train))
    alpha = np.empty((t, n_train))
    for i in range(t):
        z = x / lengthscale[i]
        sq = ((z[:, None, :] - z[None, :, :]) ** 2).sum(-1)
        k = outputscale[i] * np.exp(-0.5 * sq) + noise[i] * np.eye(n_train)
        chol[i] = np.linalg.cholesky(k)
        alpha[i] = np.linalg.solve(k, y[:, i])
    edd5 = {name: np.array([0.95 - 0.05 * j, 0.93 - 0.05 * j, 0.0, -0.22 - 0.03 * j, 0.22 + 0.03 * j])
            for j, name in enumerate(terrains)}
    model = GPModel(
        terrains=list(terrains), tasks=task_names(list(terrains)), theta=SYNTHETIC_THETA.copy(), edd5=edd5,
        domain_lo=DOMAIN_LO.copy(), domain_hi=DOMAIN_HI.copy(), train_x=x, lengthscale=lengthscale,
        outputscale=outputscale, noise=noise, chol=chol, alpha=alpha, dt=0.1,
    )
    model.set_grid(build_grid(model, nodes))
    if set(terrains) <= set(SHIPPED_GROUNDS):  # the Jackal's grounds: the shipped, plant-fitted calibration
        model.calibration = shipped_calibration(list(terrains))
    return model
