"""Learning a new ground while driving: collect its one-step residuals, fit its GP, append it to the robot profile.

Pure: arrays in, a `GPModel` out (no files, no threads; the terrain service runs `learn_ground` off its cycle and
saves the result, gpmppi.gp.profile_store).

**The samples.** Each step on the new ground gives the GP input `x = [v_ref, omega_ref, v, omega]` and the residual
`y = next (v, omega) - the nominal model's one-step prediction` (what every ground's GP learns, gpmppi.gp.train), and
the change of command `du` since the previous step (for the terrain estimator's command-change gain).

**The fit.** The profile stores one input set shared by all 2M tasks. A new ground's inputs are appended to it and
every task's Cholesky factor is extended block-diagonally: the old tasks get `BIG * I` over the new inputs and zeros in
alpha there (their mean and variance change by less than n (s / BIG)^2, i.e. not at all), the new tasks get `BIG * I`
over the old inputs. So nothing about the trained grounds changes, and the planner's kernels, the grid table and the
file format take the learned ground as they are.

Two forms of the new ground's GP (`LearnSettings.hyperparameters`, compared in docs/new_ground.md):

- `kept` (the default): the hyperparameters of the nearest trained ground (the one whose GP mean explains the samples
  best), and that ground's mean as the prior mean: alpha over the old inputs is the nearest ground's, and over the
  new inputs `(K + noise I)^-1 (y - m_nearest)`. Where the robot has not driven the new ground, it predicts like the
  nearest ground, with the prior's variance (the new block only shrinks it where the samples are).
- `fitted`: hyperparameters fitted on the samples (gpmppi.gp.fit, GPyTorch), zero prior mean, as `gpmppi train` fits
  a ground.

**The calibration** the Bayesian estimator needs per ground (gpmppi.profile.terrain_calibration) comes from the samples
and the learned GP: the command-change gain is the least-squares gain of `y - m_new` on `du`; the steady response map
is the nearest ground's, moved by the difference of the two grounds' GP-implied steady states (the fixed point of
`v <- nominal(v, u) + m(u, v)` on the map's grid, which cancels the bias the GP's missing hidden states put into the
implied map); the rate is the nearest ground's.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from gpmppi.gp.grid_table import GridTable, grid_axes, predict_dense
from gpmppi.gp.model_file import GPModel, task_names
from gpmppi.models.dynamic_unicycle import velocity_step_exact
from gpmppi.profile.response import TerrainResponse
from gpmppi.profile.terrain_calibration import TerrainCalibration

BIG = 1e6  # the Cholesky diagonal over another ground's inputs: a block that adds nothing to the variance
LOCAL_NEIGHBOURS = 3  # each conditioning input's target: the mean of this many nearest samples (as gpmppi train)
STEADY_ITERS = 60  # fixed-point steps of the GP-implied steady state (the rate of the model is ~0.3 a step)


class TooLittleData(ValueError):  # noqa: N818 - a domain error named for what the user reads
    """The samples cannot make a ground: the message says what was found, what is needed, and what to drive."""


@dataclass(frozen=True)
class LearnSettings:
    """How a new ground is learned."""

    min_samples: int = 300  # steps on the ground before a fit (10 Hz: 30 s)
    max_points: int = 150  # conditioning inputs of the new ground's GP (k-means centres of the samples)
    min_v_spread: float = 0.1  # the samples' forward speeds must span at least this [m/s] (standing still: none)
    hyperparameters: Literal["kept", "fitted"] = "kept"  # see the module docstring
    iters: int = 100  # fitted: Adam steps
    seed: int = 0


@dataclass
class GroundSamples:
    """The steps collected on one ground: GP inputs (N, 4), residuals (N, 2), command changes (N, 2)."""

    theta: np.ndarray
    dt: float
    x: list[np.ndarray] = field(default_factory=list)
    y: list[np.ndarray] = field(default_factory=list)
    du: list[np.ndarray] = field(default_factory=list)
    steps: list[np.ndarray] = field(default_factory=list)  # each step as it came: state (5), command (2), next (5)
    _u_prev: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.x)

    def add(self, state: np.ndarray, command: np.ndarray, next_state: np.ndarray) -> None:
        """One step: state (5,) at t, command (2,) applied over [t, t + dt), next_state (5,) at t + dt (taken as
        following the previous step; `gap()` when one was skipped)."""
        s = np.asarray(state, dtype=np.float64).reshape(5)
        u = np.asarray(command, dtype=np.float64).reshape(2)
        s1 = np.asarray(next_state, dtype=np.float64).reshape(5)
        if not (np.all(np.isfinite(s)) and np.all(np.isfinite(u)) and np.all(np.isfinite(s1))):
            return  # a non-finite step teaches nothing
        pv, pw = velocity_step_exact(self.theta, s[3:4].copy(), s[4:5].copy(), u[0:1].copy(), u[1:2].copy(), self.dt)
        self.x.append(np.array([u[0], u[1], s[3], s[4]]))
        self.y.append(np.array([s1[3] - pv[0], s1[4] - pw[0]]))
        self.du.append(np.zeros(2) if self._u_prev is None else u - self._u_prev)
        self.steps.append(np.concatenate([s, u, s1]))
        self._u_prev = u

    def gap(self) -> None:
        """The next step does not follow the last one: its command change is unknown (taken as 0)."""
        self._u_prev = None

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if not self.x:
            return np.zeros((0, 4)), np.zeros((0, 2)), np.zeros((0, 2))
        return np.stack(self.x), np.stack(self.y), np.stack(self.du)


@dataclass
class LearnReport:
    """What a fit did: the ground's name, its nearest trained ground, the samples and their one-step RMSE."""

    name: str
    nearest: str
    samples: int
    points: int
    hyperparameters: str
    rmse_nominal: tuple[float, float]  # (v, omega) of the nominal model alone on the samples
    rmse_nearest: tuple[float, float]  # with the nearest ground's GP
    rmse_learned: tuple[float, float]  # with the learned GP (in-sample)

    def line(self) -> str:
        return (f"learned ground {self.name!r} from {self.samples} steps ({self.points} inputs, hyperparameters "
                f"{self.hyperparameters} from {self.nearest!r}); one-step RMSE v/omega nominal "
                f"{self.rmse_nominal[0]:.4f}/{self.rmse_nominal[1]:.4f}, {self.nearest} "
                f"{self.rmse_nearest[0]:.4f}/{self.rmse_nearest[1]:.4f}, learned "
                f"{self.rmse_learned[0]:.4f}/{self.rmse_learned[1]:.4f}")


def model_version(model: GPModel) -> int:
    """The profile's model version: how many grounds were learned into it online (0: as `gpmppi train` wrote it).
    Kept in the profile (its fit report's `learned` list), so a restarted service counts on from it."""
    return len((model.fit_report or {}).get("learned", []))


def next_name(model: GPModel) -> str:
    """`new-1`, `new-2`, ...: the first such name the model does not have."""
    k = 1
    while f"new-{k}" in model.terrains:
        k += 1
    return f"new-{k}"


def check_samples(model: GPModel, name: str, x: np.ndarray, settings: LearnSettings) -> None:
    """TooLittleData (one line: what was found, what is needed) when the samples cannot make ground `name`."""
    if name in model.terrains:
        raise TooLittleData(f"ground {name!r} is already in the profile {list(model.terrains)}; name the new one "
                            "differently")
    if len(x) < settings.min_samples:
        raise TooLittleData(f"ground {name!r}: {len(x)} steps collected, at least {settings.min_samples} needed "
                            f"({settings.min_samples * model.dt:.0f} s of driving on it); not added")
    spread = float(np.ptp(x[:, 2])) if len(x) else 0.0
    if spread < settings.min_v_spread:
        raise TooLittleData(f"ground {name!r}: its steps span {spread:.3f} m/s of forward speed, at least "
                            f"{settings.min_v_spread} m/s needed (drive it, not stand on it); not added")


def nearest_ground(model: GPModel, x: np.ndarray, y: np.ndarray) -> tuple[int, np.ndarray]:
    """(index of the trained ground whose GP mean explains y best in units of its noise, the means (N, 2M))."""
    mean, _ = predict_dense(model, x)
    noise = model.noise.reshape(-1, 2)
    err = [np.mean(np.sum((y - mean[:, 2 * m:2 * m + 2]) ** 2 / noise[m], axis=1)) for m in range(model.n_terrains)]
    return int(np.argmin(err)), mean


def conditioning_set(x: np.ndarray, y: np.ndarray, points: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(inputs (n, 4), targets (n, 2)): k-means centres of the samples and the mean of each one's nearest samples
    (standardized input distance), as `gpmppi train` makes a ground's targets from a log."""
    # here, not at the top: sklearn costs the terrain service ~1 s to import, and only a ground's fit uses it
    from sklearn.cluster import KMeans
    from sklearn.neighbors import NearestNeighbors

    scale = x.std(0) + 1e-9
    n = min(points, len(x))
    centres = KMeans(n_clusters=n, random_state=seed, n_init=1).fit(x / scale).cluster_centers_
    k = min(LOCAL_NEIGHBOURS, len(x))
    nbr = NearestNeighbors(n_neighbors=k).fit(x / scale).kneighbors(centres, return_distance=False)
    return centres * scale, y[nbr].mean(axis=1)


def _block_factor(z: np.ndarray, target: np.ndarray, ls: np.ndarray, os_: float, noise: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Lower Cholesky factor of K + noise I at z and (K + noise I)^-1 target."""
    from scipy.linalg import cho_solve  # here: scipy.linalg is ~0.15 s of a service's start, and only a fit uses it

    a = z / ls
    sq = ((a[:, None, :] - a[None, :, :]) ** 2).sum(-1)
    chol = np.linalg.cholesky(os_ * np.exp(-0.5 * sq) + noise * np.eye(len(z)))
    return chol, cho_solve((chol, True), target)


def _append_tasks(model: GPModel, name: str, near: str, z: np.ndarray, chol_new: np.ndarray, alpha_old: np.ndarray,
                  alpha_new: np.ndarray, ls: np.ndarray, os_: np.ndarray, noise: np.ndarray) -> GPModel:
    """The model with ground `name`'s two tasks appended (block-diagonal factors, see the module docstring; its
    EDD5 and lateral slip are those of the nearest ground `near`); chol_new (2, m, m) and alpha_new (2, m) over z;
    alpha_old (2, n) the new tasks' alpha over the old inputs."""
    n, m, t = len(model.train_x), len(z), model.n_tasks
    chol = np.zeros((t + 2, n + m, n + m))
    chol[:t, :n, :n] = model.chol
    chol[:t, n:, n:] = BIG * np.eye(m)
    chol[t:, :n, :n] = BIG * np.eye(n)
    chol[t:, n:, n:] = chol_new
    alpha = np.zeros((t + 2, n + m))
    alpha[:t, :n] = model.alpha
    alpha[t:, :n] = alpha_old
    alpha[t:, n:] = alpha_new
    terrains = [*model.terrains, name]
    return GPModel(
        terrains=terrains, tasks=task_names(terrains), theta=model.theta.copy(),
        edd5={**model.edd5, name: model.edd5[near].copy()},
        domain_lo=model.domain_lo, domain_hi=model.domain_hi, train_x=np.vstack([model.train_x, z]),
        lengthscale=np.vstack([model.lengthscale, ls]), outputscale=np.concatenate([model.outputscale, os_]),
        noise=np.concatenate([model.noise, noise]), chol=chol, alpha=alpha, dt=model.dt,
        lateral_slip={**model.lateral_slip, name: model.lateral_slip[near].copy()} if model.lateral_slip else None,
        fit_report=model.fit_report, robot=model.robot, made_by=model.made_by,
        novelty=model.novelty,  # the novelty test's calibration is one for all grounds: it carries over as it is
    )


def _kernel(x: np.ndarray, z: np.ndarray, ls: np.ndarray, os_: float) -> np.ndarray:
    a, b = x / ls, z / ls
    sq = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
    return os_ * np.exp(-0.5 * np.maximum(sq, 0.0))


def task_mean(model: GPModel, task: int, x: np.ndarray, chunk: int = 8192) -> np.ndarray:
    """(P,) the exact GP mean of one task at x (P, 4), without its variance."""
    out = np.empty(len(x))
    ls, os_ = model.lengthscale[task], float(model.outputscale[task])
    for s in range(0, len(x), chunk):
        out[s:s + chunk] = _kernel(x[s:s + chunk], model.train_x, ls, os_) @ model.alpha[task]
    return out


def implied_steady(model: GPModel, ground: int, v_ref: np.ndarray, omega_ref: np.ndarray) -> np.ndarray:
    """(A, B, 2) the steady (v, omega) ground `ground`'s one-step model (nominal + GP mean) settles to under each held
    command of the grid (a fixed-point iteration from the command)."""
    u = np.stack(np.meshgrid(v_ref, omega_ref, indexing="ij"), axis=-1).reshape(-1, 2)
    v, w = u[:, 0].copy(), u[:, 1].copy()
    for _ in range(STEADY_ITERS):
        x = np.column_stack([u, v, w])
        pv, pw = velocity_step_exact(model.theta, v.copy(), w.copy(), u[:, 0].copy(), u[:, 1].copy(), model.dt)
        v, w = pv + task_mean(model, 2 * ground, x), pw + task_mean(model, 2 * ground + 1, x)
    return np.stack([v, w], axis=-1).reshape(len(v_ref), len(omega_ref), 2)


def _calibration(model: GPModel, new: GPModel, nearest: int, x: np.ndarray, y: np.ndarray, du: np.ndarray
                 ) -> TerrainCalibration | None:
    """The old calibration with the new ground's appended (None when the model has none)."""
    cal = model.calibration
    if cal is None:
        return None
    m = new.n_terrains - 1
    mean, _ = predict_dense(new, x)
    e = y - mean[:, 2 * m:2 * m + 2]
    gain = np.sum(du * e, axis=0) / np.maximum(np.sum(du * du, axis=0), 1e-12)
    r = cal.response
    shift = implied_steady(new, m, r.v_ref, r.omega_ref) - implied_steady(new, nearest, r.v_ref, r.omega_ref)
    steady = np.concatenate([r.steady, (r.steady[nearest] + shift)[None]])
    response = TerrainResponse(r.v_ref, r.omega_ref, (*r.terrains, new.terrains[m]), steady,
                               np.vstack([r.rate, r.rate[nearest]]))
    return TerrainCalibration(response.terrains, np.vstack([cal.command_gain, gain]), response)


def _extend_grid(model: GPModel, new: GPModel, near: int, kept: bool, z: np.ndarray, chol_z: np.ndarray) -> None:
    """Attach the old grid table with the new tasks' channels added at the same nodes (when the old model has one).

    A new task's mean is its prior mean (kept: the nearest ground's mean channel; fitted: 0) plus its block's over z;
    its variance is its block's alone (the old inputs' block adds nothing, see the module docstring)."""
    if not model.has_stored_grid():
        return
    from scipy.linalg import solve_triangular  # here: scipy.linalg is ~0.15 s of a service's start

    old = model.grid()
    dims = old.dims
    pts = np.stack(np.meshgrid(*grid_axes(old.lo, old.hi, dims), indexing="ij"), axis=-1).reshape(-1, 4)
    t, n = model.n_tasks, len(model.train_x)
    tab = old.table.reshape(-1, 2 * t)
    mean = np.zeros((len(pts), 2))
    var = np.zeros((len(pts), 2))
    for o in range(2):
        task = t + o
        ls, os_ = new.lengthscale[task], float(new.outputscale[task])
        if kept:
            mean[:, o] = tab[:, 2 * near + o]
        for s in range(0, len(pts), 8192):
            k = _kernel(pts[s:s + 8192], z, ls, os_)
            mean[s:s + 8192, o] += k @ new.alpha[task, n:]
            v = solve_triangular(chol_z[o], k.T, lower=True, check_finite=False)
            var[s:s + 8192, o] = np.maximum(os_ - (v * v).sum(0), 0.0)
    table = np.concatenate([tab[:, :t], mean, tab[:, t:], var], axis=1).reshape(*dims, 2 * (t + 2))
    new.set_grid(GridTable(np.ascontiguousarray(table), old.lo.copy(), old.inv_step.copy()))


def learn_ground(model: GPModel, samples: GroundSamples, name: str | None = None,
                 settings: LearnSettings | None = None) -> tuple[GPModel, LearnReport]:
    """The profile with the ground of `samples` appended as `name` (None: `next_name`), and what the fit did.

    Raises TooLittleData (one line) when the samples cannot make a ground (`check_samples`)."""
    cfg = settings or LearnSettings()
    name = next_name(model) if name is None else name.strip()
    if not re.fullmatch(r"[A-Za-z0-9_-]{1,64}", name):
        raise TooLittleData(f"ground name {name!r}: use 1-64 letters, digits, '_' or '-'; not added")
    x, y, du = samples.arrays()
    check_samples(model, name, x, cfg)
    near, mean = nearest_ground(model, x, y)
    m_near = mean[:, 2 * near:2 * near + 2]
    z, target = conditioning_set(x, y, cfg.max_points, cfg.seed)
    tv, tw = 2 * near, 2 * near + 1
    if cfg.hyperparameters == "kept":
        ls, os_, noise = model.lengthscale[[tv, tw]], model.outputscale[[tv, tw]], model.noise[[tv, tw]]
        prior = np.column_stack([task_mean(model, tv, z), task_mean(model, tw, z)])  # the prior mean
        alpha_old = model.alpha[[tv, tw]]
    else:
        from gpmppi.gp.fit import clip_outliers, fit_hyperparameters

        target = clip_outliers(target.T)[0].T
        hp, _ = fit_hyperparameters(z, target.T, cfg.iters, cfg.seed)
        ls, os_, noise = hp.lengthscale, hp.outputscale, hp.noise
        prior = np.zeros_like(target)
        alpha_old = np.zeros((2, len(model.train_x)))
    factors = [_block_factor(z, target[:, o] - prior[:, o], ls[o], float(os_[o]), float(noise[o])) for o in range(2)]
    new = _append_tasks(model, name, model.terrains[near], z, np.stack([f[0] for f in factors]), alpha_old,
                        np.stack([f[1] for f in factors]), ls, os_, noise)
    new.calibration = _calibration(model, new, near, x, y, du)
    _extend_grid(model, new, near, cfg.hyperparameters == "kept", z, np.stack([f[0] for f in factors]))
    learned = np.column_stack([task_mean(new, new.n_tasks - 2, x), task_mean(new, new.n_tasks - 1, x)])

    def rmse(e: np.ndarray) -> tuple[float, float]:
        r = np.sqrt(np.mean(e**2, axis=0))
        return float(r[0]), float(r[1])

    report = LearnReport(name, model.terrains[near], len(x), len(z), cfg.hyperparameters, rmse(y), rmse(y - m_near),
                         rmse(y - learned))
    entry = {"ground": name, "steps": len(x), "inputs": len(z), "nearest": report.nearest,
             "hyperparameters": cfg.hyperparameters}
    new.fit_report = {**(model.fit_report or {}), "learned": [*(model.fit_report or {}).get("learned", []), entry]}
    return new, report
