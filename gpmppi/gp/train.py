"""Training the batch of per-terrain residual GPs (pure: arrays in, a GPModel and a fit report out).

Pipeline: one-step transitions per terrain -> residual targets (measured next velocity minus the
nominal model integrated exactly over dt) -> ~300 shared training inputs chosen by k-means over the
4-D input `[v_ref, omega_ref, v, omega]` -> a batch of 2M independent exact GPs (zero mean,
ScaleKernel(RBF-ARD)) fitted with GPyTorch, or given hyperparameters -> Cholesky factors and
alphas in float64 -> a `GPModel`.

Shared training inputs. The model stores one input set for all 2M tasks (the planner then
evaluates one kernel row per input for every task). When all terrains were driven with the same
inputs (the paper's CSV), the chosen inputs are actual samples (the sample nearest each k-means
centre), so targets are measured values. Otherwise (terrain logs driven separately) the inputs
are the k-means centres of the pooled data and each terrain's target at a centre is the mean of
that terrain's `LOCAL_NEIGHBOURS` nearest samples (standardized input distance): a local average
that exists for every terrain at every centre and also averages out measurement noise.

Steady inputs (`steady_points`, 0 by default: then nothing changes). The GP's inputs lack the plant's hidden states
(the motors' integrators), so a settled held command and a transient through the same (command, velocity) can have
different residuals, and the excitation's rows are mostly transient: in steady driving near the top speed the GP is
off by several novelty spreads (gpmppi/terrain/steady_bias.py). With `steady_points` K, K of the inputs are the
k-means centres of the pooled settled rows (the command held `STEADY_HELD_S` or longer), each terrain's target there
the mean of its `STEADY_NEIGHBOURS` nearest settled rows; the other inputs are chosen as before. Measured, it does not
remove that bias (docs/terrain_identification.md, "Steady driving near the top speed"): an option to try per robot.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cho_solve
from sklearn.cluster import KMeans
from sklearn.neighbors import NearestNeighbors

from gpmppi.gp.fit import Hyperparameters, clip_outliers, fit_hyperparameters
from gpmppi.gp.grid import predict_dense
from gpmppi.gp.model_file import GPModel, task_names
from gpmppi.models.dynamic_unicycle import velocity_step_exact
from gpmppi.models.lateral_slip import N_LATERAL, body_lateral_velocity, fit_lateral_slip

LOCAL_NEIGHBOURS = 3
STEADY_HELD_S = 2.0  # a row counts as settled once its command has been held this long [s]
STEADY_NEIGHBOURS = 5  # settled rows averaged into a steady input's target
# "seeded": the k-means of the inputs, the restarts and the validation fold all drawn by the seed (the earlier fit);
# "stable": the inputs' k-means and the restarts started alike whatever the seed, the choice among the restarts' steps
# by leave-one-out on all the inputs (`gpmppi.gp.fit`, selection "loo"): the seed draws only the held-out split
FITS = ("seeded", "stable")
DEFAULT_FIT = "seeded"
DESIGN_SEED = 0  # "stable": the k-means initialisation's seed, whatever the fit's


@dataclass
class Transitions:
    """One terrain's one-step data: inputs x (N, 4) = [v_ref, omega_ref, v, omega], residual (N, 2)."""

    x: np.ndarray
    residual: np.ndarray
    next_vw: np.ndarray | None = None  # measured next (v, omega), when known
    lateral_slip: np.ndarray | None = None  # (a, b) of `gpmppi.models.lateral_slip`, when poses were logged
    held_s: np.ndarray | None = None  # (N,) how long each row's command had been held [s], when a time series

    def rows(self, mask: np.ndarray) -> Transitions:
        """The rows of `mask` (inputs, residuals and, when known, how long each command had been held)."""
        return Transitions(self.x[mask], self.residual[mask],
                           held_s=None if self.held_s is None else self.held_s[mask])


def held_seconds(v_ref: np.ndarray, w_ref: np.ndarray, seg: np.ndarray, dt: float) -> np.ndarray:
    """(n,) per tick, how long its command had been held (unchanged within 1e-4 in the same segment) [s]: 0 at a
    change."""
    vr, wr, sg = (np.asarray(a) for a in (v_ref, w_ref, seg))
    same = np.zeros(len(vr), dtype=bool)
    same[1:] = (sg[1:] == sg[:-1]) & (np.abs(np.diff(vr)) < 1e-4) & (np.abs(np.diff(wr)) < 1e-4)
    # ticks since the last change: a running count reset where `same` is False
    idx = np.arange(len(vr))
    last_change = np.maximum.accumulate(np.where(same, 0, idx))
    return (idx - last_change) * dt


@dataclass
class TerrainFit:
    terrain: str
    n_eval: int
    rmse_nominal: tuple[float, float]  # (v, omega)
    rmse_gp: tuple[float, float]
    nll: tuple[float, float]  # mean negative log predictive density per step


@dataclass
class FitReport:
    eval_set: str  # "held-out" / "test data" / "training data"
    terrains: list[TerrainFit] = field(default_factory=list)
    final_loss: float | None = None
    held_out: bool = False  # evaluated on data the model was not conditioned on
    clipped: int = 0  # training targets clipped as outliers (`fit.clip_outliers`)
    hyperparameters: str = "fitted"  # or "given"

    def gp_worse_than_nominal(self) -> list[dict]:
        """Tasks whose GP predicts worse than the nominal model alone on held-out data (none when not held out)."""
        if not self.held_out:
            return []
        return [
            {"terrain": f.terrain, "output": out, "rmse_nominal": f.rmse_nominal[o], "rmse_gp": f.rmse_gp[o],
             "eval_set": self.eval_set, "steps": f.n_eval}
            for f in self.terrains for o, out in enumerate(("v", "omega")) if f.rmse_gp[o] > f.rmse_nominal[o]
        ]

    def to_metadata(self) -> dict:
        """The report as the model file's `fit` metadata (JSON types only)."""
        return {
            "eval_set": self.eval_set, "held_out": self.held_out, "hyperparameters": self.hyperparameters,
            "clipped_targets": self.clipped,
            "tasks": [
                {"terrain": f.terrain, "output": out, "steps": f.n_eval, "rmse_nominal": f.rmse_nominal[o],
                 "rmse_gp": f.rmse_gp[o], "nll": f.nll[o]}
                for f in self.terrains for o, out in enumerate(("v", "omega"))
            ],
            "gp_worse_than_nominal": self.gp_worse_than_nominal(),
        }


def residual_targets(theta: np.ndarray, x: np.ndarray, next_vw: np.ndarray, dt: float) -> np.ndarray:
    """Measured next (v, omega) minus the nominal model integrated exactly over dt."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    pv, pw = velocity_step_exact(
        np.asarray(theta, dtype=np.float64), x[:, 2].copy(), x[:, 3].copy(), x[:, 0].copy(), x[:, 1].copy(), dt
    )
    return np.column_stack([next_vw[:, 0] - pv, next_vw[:, 1] - pw])


def fit_lateral_from_series(s: dict[str, np.ndarray], dt: float) -> np.ndarray | None:
    """Lateral slip (a, b) of one terrain's series from the sideways velocity between consecutive poses against
    the step's mean speed and yaw rate; None when the series has no poses."""
    if not all(k in s for k in ("x", "y", "yaw")):
        return None
    pose = [np.asarray(s[k], dtype=np.float64) for k in ("x", "y", "yaw")]
    if any(not np.all(np.isfinite(p)) for p in pose):
        raise ValueError("non-finite poses in the data")
    i, vy = body_lateral_velocity(*pose, dt, np.asarray(s["seg"]))
    v, w = np.asarray(s["v"], dtype=np.float64), np.asarray(s["w"], dtype=np.float64)
    return fit_lateral_slip(0.5 * (v[i] + v[i + 1]), 0.5 * (w[i] + w[i + 1]), vy)


def prepare_from_series(
    series: dict[str, dict[str, np.ndarray]],
    dt: float,
    theta: np.ndarray | None = None,
    edd5: dict[str, np.ndarray] | None = None,
    seed: int = 0,
) -> tuple[dict[str, Transitions], np.ndarray, dict[str, np.ndarray]]:
    """Per-terrain time series -> (transitions with residual targets, theta, EDD5 per terrain).

    series[terrain] has equal-length arrays "v", "w" (measured at t_k), "v_ref", "w_ref" (applied
    over [t_k, t_k + dt)) and "seg" (segment id; nothing is paired across a segment change), and may have the
    poses "x", "y", "yaw": then each terrain's lateral slip is fitted too (`fit_lateral_from_series`).
    theta is identified from all terrains pooled when not given (the nominal model is shared), and
    each terrain's EDD5 from its commands and the velocities measured one step later.
    """
    from gpmppi.models.identify import identify_edd5, identify_theta, one_step_pairs

    if not series:
        raise ValueError("no terrain data to train on")
    keys = ("v", "w", "v_ref", "w_ref")
    for t, s in series.items():
        missing = [k for k in (*keys, "seg") if k not in s]
        if missing:
            raise ValueError(f"terrain {t!r}: series lacks {missing}")
        if any(not np.all(np.isfinite(s[k])) for k in keys):
            raise ValueError(f"terrain {t!r}: non-finite velocities or commands in the data")
        if any(k in s and not np.all(np.isfinite(s[k])) for k in ("x", "y", "yaw")):
            raise ValueError(f"terrain {t!r}: non-finite poses in the data")
        if len(s["v"]) < 2:
            raise ValueError(f"terrain {t!r}: fewer than 2 samples")
    if theta is None:
        pooled = {k: np.concatenate([s[k] for s in series.values()]) for k in keys}
        # segment ids made unique across terrains so no pair spans two terrains
        pooled_seg = np.concatenate([np.asarray(s["seg"]) * len(series) + i for i, s in enumerate(series.values())])
        theta = identify_theta(*(pooled[k] for k in keys), dt, segment_ids=pooled_seg, seed=seed)
    sets: dict[str, Transitions] = {}
    for t, s in series.items():
        v, w, vr, wr, vn, wn = one_step_pairs(s["v"], s["w"], s["v_ref"], s["w_ref"], segment_ids=np.asarray(s["seg"]))
        x = np.column_stack([vr, wr, v, w])
        nxt = np.column_stack([vn, wn])
        held = held_seconds(s["v_ref"], s["w_ref"], s["seg"], dt)
        held_k = one_step_pairs(held, held, s["v_ref"], s["w_ref"], segment_ids=np.asarray(s["seg"]))[0]
        sets[t] = Transitions(x, residual_targets(theta, x, nxt, dt), nxt, fit_lateral_from_series(s, dt), held_k)
    if edd5 is None:
        edd5 = {t: identify_edd5(s.x[:, 0], s.x[:, 1], s.next_vw[:, 0], s.next_vw[:, 1], seed=seed)
                for t, s in sets.items()}
    return sets, np.asarray(theta, dtype=np.float64), edd5


def hyperparameters_from_json(data: dict, tasks: list[str]) -> Hyperparameters:
    """Read the paper's hyperparameter layout (lengthscale, outputscale, task_noise, shared_noise)."""
    for key in ("tasks", "lengthscale", "outputscale", "task_noise"):
        if key not in data:
            raise ValueError(f"hyperparameter file has no {key!r} field (expected the gp_hyperparameters layout)")
    names = [str(t).lower() for t in data["tasks"]]
    try:
        order = [names.index(t.lower()) for t in tasks]
    except ValueError as e:
        raise ValueError(f"hyperparameter file tasks {data['tasks']} do not cover the model tasks {tasks}") from e
    ls = np.asarray(data["lengthscale"], dtype=np.float64)
    os_ = np.asarray(data["outputscale"], dtype=np.float64)
    noise = np.asarray(data["task_noise"], dtype=np.float64) + float(data.get("shared_noise", 0.0))
    if ls.shape != (len(names), 4) or os_.shape != (len(names),) or noise.shape != (len(names),):
        raise ValueError(
            f"hyperparameter shapes lengthscale {ls.shape}, outputscale {os_.shape}, noise {noise.shape} "
            f"do not match {len(names)} tasks x 4 inputs"
        )
    hp = Hyperparameters(ls[order], os_[order], noise[order])
    for name in ("lengthscale", "outputscale", "noise"):
        a = getattr(hp, name)
        if not np.all(np.isfinite(a)) or np.any(a <= 0):
            raise ValueError(f"hyperparameter {name!r} must be finite and positive")
    return hp


def _shared_inputs(sets: dict[str, Transitions]) -> bool:
    xs = [s.x for s in sets.values()]
    return all(x.shape == xs[0].shape and np.array_equal(x, xs[0]) for x in xs[1:])


def steady_inputs(sets: dict[str, Transitions], points: int, seed: int,
                  scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x (k, 4), y (2M, k)): `points` k-means centres of the pooled settled rows (module docstring), each terrain's
    target the mean residual of its `STEADY_NEIGHBOURS` nearest settled rows (`scale`: the inputs' scale)."""
    missing = [t for t, s in sets.items() if s.held_s is None]
    if missing:
        raise ValueError(f"steady inputs need time series (how long each command was held); {missing} have none")
    settled = {t: s.x[s.held_s >= STEADY_HELD_S] for t, s in sets.items()}
    short = [t for t, x in settled.items() if len(x) < STEADY_NEIGHBOURS]
    if short:
        raise ValueError(f"steady inputs: terrains {short} have fewer than {STEADY_NEIGHBOURS} rows with the command "
                         f"held {STEADY_HELD_S:g} s or longer")
    pooled = np.concatenate(list(settled.values()))
    km = KMeans(n_clusters=min(points, len(pooled)), random_state=seed, n_init=1).fit(pooled / scale)
    ys = []
    for t, s in sets.items():
        res = s.residual[s.held_s >= STEADY_HELD_S]
        nbr = NearestNeighbors(n_neighbors=STEADY_NEIGHBOURS).fit(settled[t] / scale).kneighbors(
            km.cluster_centers_, return_distance=False)
        ys.append(res[nbr].mean(axis=1).T)
    return km.cluster_centers_ * scale, np.concatenate(ys, axis=0)


def select_training_data(
    sets: dict[str, Transitions], points: int, seed: int, steady_points: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """(train_x (n, 4), train_y (2M, n)) with shared inputs (see the module docstring); `steady_points` of them at
    settled rows (0: none)."""
    if not 0 <= steady_points < points:
        raise ValueError(f"steady points {steady_points} must be in [0, {points})")
    terrains = list(sets)
    if _shared_inputs(sets):
        if steady_points:
            raise ValueError("steady inputs need time series (how long each command was held); the data has none")
        x = sets[terrains[0]].x
        if len(x) <= points:
            idx = np.arange(len(x))
        else:
            scale = x.std(0) + 1e-9
            km = KMeans(n_clusters=points, random_state=seed, n_init=1).fit(x / scale)
            nn = NearestNeighbors(n_neighbors=1).fit(x / scale)
            idx = np.unique(nn.kneighbors(km.cluster_centers_, return_distance=False)[:, 0])
        ys = [sets[t].residual[idx].T for t in terrains]
        return x[idx].copy(), np.concatenate(ys, axis=0)
    pooled = np.concatenate([s.x for s in sets.values()])
    scale = pooled.std(0) + 1e-9
    n_clusters = min(points - steady_points, len(pooled))
    km = KMeans(n_clusters=n_clusters, random_state=seed, n_init=1).fit(pooled / scale)
    centres = km.cluster_centers_
    ys = []
    for t in terrains:
        s = sets[t]
        k = min(LOCAL_NEIGHBOURS, len(s.x))
        nbr = NearestNeighbors(n_neighbors=k).fit(s.x / scale).kneighbors(centres, return_distance=False)
        ys.append(s.residual[nbr].mean(axis=1).T)  # (2, n)
    if steady_points:
        sx, sy = steady_inputs(sets, steady_points, seed, scale)
        return np.concatenate([centres * scale, sx]), np.concatenate([np.concatenate(ys, axis=0), sy], axis=1)
    return centres * scale, np.concatenate(ys, axis=0)


def factorize(train_x: np.ndarray, train_y: np.ndarray, hp: Hyperparameters) -> tuple[np.ndarray, np.ndarray]:
    """Lower Cholesky factors of K + noise I and alpha = (K + noise I)^-1 y, per task (float64)."""
    n_tasks, n = train_y.shape
    chol = np.empty((n_tasks, n, n))
    alpha = np.empty((n_tasks, n))
    for t in range(n_tasks):
        z = train_x / hp.lengthscale[t]
        sq = ((z[:, None, :] - z[None, :, :]) ** 2).sum(-1)
        k = hp.outputscale[t] * np.exp(-0.5 * sq) + hp.noise[t] * np.eye(n)
        try:
            chol[t] = np.linalg.cholesky(k)
        except np.linalg.LinAlgError as e:
            raise ValueError(f"task {t}: kernel matrix is not positive definite (duplicate inputs, tiny noise?)") from e
        alpha[t] = cho_solve((chol[t], True), train_y[t])
    return chol, alpha


def domain_box(x: np.ndarray, pad_fraction: float = 0.05, min_pad: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = x.min(0), x.max(0)
    pad = np.maximum(pad_fraction * (hi - lo), min_pad)
    return lo - pad, hi + pad


def evaluate_fit(model: GPModel, sets: dict[str, Transitions], eval_set: str) -> FitReport:
    """Per terrain: one-step RMSE of nominal alone (|residual|) vs nominal + GP mean, and the NLL."""
    report = FitReport(eval_set=eval_set)
    for m, t in enumerate(model.terrains):
        s = sets[t]
        if len(s.x) == 0:
            continue
        mean, var = predict_dense(model, s.x)
        rn, rg, nll = [], [], []
        for o in range(2):
            task = 2 * m + o
            err = s.residual[:, o] - mean[:, task]
            rn.append(float(np.sqrt(np.mean(s.residual[:, o] ** 2))))
            rg.append(float(np.sqrt(np.mean(err**2))))
            pv = var[:, task] + model.noise[task]
            nll.append(float(np.mean(0.5 * np.log(2 * np.pi * pv) + 0.5 * err**2 / pv)))
        report.terrains.append(TerrainFit(t, len(s.x), tuple(rn), tuple(rg), tuple(nll)))
    return report


def split_holdout(
    sets: dict[str, Transitions], fraction: float, seed: int
) -> tuple[dict[str, Transitions], dict[str, Transitions]]:
    """Seeded random split into (train, held-out); shared-input sets are split with the same rows."""
    if fraction <= 0:
        return sets, {t: Transitions(s.x[:0], s.residual[:0]) for t, s in sets.items()}
    rng = np.random.default_rng(seed)
    shared = _shared_inputs(sets)
    first_mask: np.ndarray | None = None
    train, held = {}, {}
    for t, s in sets.items():
        if shared and first_mask is not None:
            mask = first_mask
        else:
            mask = rng.random(len(s.x)) < fraction
            first_mask = mask
        train[t] = s.rows(~mask)
        held[t] = s.rows(mask)
        if len(train[t].x) == 0:
            raise ValueError(f"terrain {t!r}: no training data left after holding out {fraction:.0%}")
    return train, held


def train_model(
    sets: dict[str, Transitions],
    theta: np.ndarray,
    edd5: dict[str, np.ndarray],
    dt: float = 0.1,
    points: int = 300,
    iters: int = 200,
    seed: int = 0,
    hyperparameters: dict | None = None,
    holdout: float = 0.2,
    test_sets: dict[str, Transitions] | None = None,
    steady_points: int = 0,
    fit: str = DEFAULT_FIT,
) -> tuple[GPModel, FitReport]:
    """Fit the GP batch to per-terrain residual transitions; return the model and its fit report. `steady_points`:
    of the `points` inputs, this many at settled rows (module docstring; 0: none); `fit`: one of `FITS` (what the seed
    draws)."""
    if not sets:
        raise ValueError("no terrain data to train on")
    for t, s in sets.items():
        if len(s.x) == 0:
            raise ValueError(f"terrain {t!r} has no transitions")
        if s.x.shape[1:] != (4,) or s.residual.shape != (len(s.x), 2):
            raise ValueError(f"terrain {t!r}: inputs {s.x.shape} / residuals {s.residual.shape} malformed")
        if not (np.all(np.isfinite(s.x)) and np.all(np.isfinite(s.residual))):
            raise ValueError(f"terrain {t!r}: non-finite inputs or residuals")
    missing = [t for t in sets if t not in edd5]
    if missing:
        raise ValueError(f"no EDD5 parameters for terrains {missing}")
    if points < 2:
        raise ValueError(f"--points must be at least 2, got {points}")
    if fit not in FITS:
        raise ValueError(f"fit must be one of {FITS}, got {fit!r}")
    terrains = list(sets)
    tasks = task_names(terrains)
    train_sets, held = split_holdout(sets, 0.0 if test_sets is not None else holdout, seed)
    train_x, train_y = select_training_data(train_sets, points, seed if fit == "seeded" else DESIGN_SEED,
                                            steady_points)
    loss, clipped = None, 0
    if hyperparameters is not None:  # the paper's procedure: its hyperparameters, its targets as they are
        hp = hyperparameters_from_json(hyperparameters, tasks)
    else:
        train_y, clipped = clip_outliers(train_y)
        hp, diag = fit_hyperparameters(train_x, train_y, iters, seed,
                                        selection="fold" if fit == "seeded" else "loo")
        loss = diag.final_loss
    chol, alpha = factorize(train_x, train_y, hp)
    lo, hi = domain_box(np.concatenate([s.x for s in train_sets.values()]))
    model = GPModel(
        terrains=terrains, tasks=tasks, theta=np.asarray(theta, dtype=np.float64),
        edd5={t: np.asarray(edd5[t], dtype=np.float64) for t in terrains},
        domain_lo=lo, domain_hi=hi, train_x=train_x, lengthscale=hp.lengthscale, outputscale=hp.outputscale,
        noise=hp.noise, chol=chol, alpha=alpha, dt=dt,
        lateral_slip={t: np.zeros(N_LATERAL) if sets[t].lateral_slip is None else sets[t].lateral_slip
                      for t in terrains},
    )
    if test_sets is not None:
        report = evaluate_fit(model, {t: test_sets[t] for t in terrains}, "test data")
    elif holdout > 0:
        report = evaluate_fit(model, held, f"held-out {holdout:.0%}")
    else:
        report = evaluate_fit(model, train_sets, "training data (no held-out set)")
    report.held_out = test_sets is not None or holdout > 0
    report.final_loss, report.clipped = loss, clipped
    report.hyperparameters = "given" if hyperparameters is not None else "fitted"
    model.fit_report = report.to_metadata()
    return model, report
