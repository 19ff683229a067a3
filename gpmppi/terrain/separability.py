"""How well the trained terrains can be told apart on transitions a robot actually drove.

Pure: recorded arrays in (measured states (T+1, 5), the commands applied between them (T, 2), the terrain under the
robot per step), numbers out. For each step the measured one-step velocity residual `y` (next velocity minus the
nominal model's step) is compared with every terrain's exact GP prediction: mean `m_i` and predictive variance
`s_i^2 = latent variance + likelihood noise` (the noise the GP was trained with). From that:

- `d'` per step: |m_true - m_j| / s_true, per output (v, omega): how far apart two terrains' predictions are in
  units of the spread a single step has;
- the per-step log-likelihood ratio `log N(y; m_true, s_true^2) - log N(y; m_j, s_j^2)` (both outputs), its mean
  (nats per step: the evidence a step carries) and, summed over sliding windows of W steps, the fraction of windows
  in which the true terrain wins;
- calibration: the mean of `((y - m_true) / s_true)^2`, 1 when the GP's predictive variance is the residuals' real
  spread, above 1 when the real residuals scatter more (sensor noise, motor states the GP inputs do not carry);
- the confusion matrix of the argmax over terrains of the window log-likelihood (rows: true terrain, columns:
  chosen), and the same for the squared-error fit the paper's estimator minimises (no predictive variance);
- `pooled_separability`: all of it over a set of recorded runs, as the GP has it, with the noise model made honest
  (`calibrated`) and with the shipped per-terrain command-change gains.

And replaying an estimator on recorded steps as the closed loop feeds it (`replay`), with what to score the weights
by beyond the evaluation's metrics: how fast they follow a change of ground (`switch_response`) and how often the
top terrain changes after the settling time (`top_changes`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpmppi.gp.exact import ExactPredictor
from gpmppi.gp.model_file import GPModel
from gpmppi.models.dynamic_unicycle import velocity_step_exact
from gpmppi.terrain.estimate import EstimatorLike
from gpmppi.terrain.settings import EstimatorConfig, profile_calibration


@dataclass
class Transitions:
    """Per step k: the measured residual and every terrain's GP prediction at the step's GP input."""

    y: np.ndarray  # (n, 2) measured next (v, omega) minus the nominal step [m/s, rad/s]
    mean: np.ndarray  # (n, M, 2) GP mean residual per terrain
    var: np.ndarray  # (n, M, 2) GP predictive variance per terrain (latent + likelihood noise)
    terrain: list[str]  # (n,) the terrain under the robot
    segment: np.ndarray | None = None  # (n,) run id of each step (pooled runs): windows never straddle two runs

    def labels(self) -> list[str]:
        """Per step a label that changes where a window must not cross: a terrain change or a new run."""
        if self.segment is None:
            return list(self.terrain)
        return [f"{t}#{int(s)}" for t, s in zip(self.terrain, self.segment, strict=True)]


def transitions(
    model: GPModel, states: np.ndarray, commands: np.ndarray, terrains: list[str],
    extra_var: tuple[float, float] = (0.0, 0.0),
) -> Transitions:
    """Residuals and GP predictions of the steps states[k] -> states[k + 1] under commands[k].

    `extra_var` [(m/s)^2, (rad/s)^2] is added to every predictive variance (e.g. measurement noise the GP's training
    data did not have).
    """
    x = np.asarray(states, dtype=np.float64)
    u = np.asarray(commands, dtype=np.float64)
    n = u.shape[0]
    if x.shape != (n + 1, 5) or u.shape != (n, 2) or len(terrains) != n:
        raise ValueError(f"need states (n+1, 5), commands (n, 2), n terrains; got {x.shape}, {u.shape}, "
                         f"{len(terrains)}")
    v1, w1 = velocity_step_exact(model.theta, x[:-1, 3].copy(), x[:-1, 4].copy(), u[:, 0].copy(), u[:, 1].copy(),
                                 model.dt)
    y = np.stack([x[1:, 3] - v1, x[1:, 4] - w1], axis=1)
    gp_in = np.stack([u[:, 0], u[:, 1], x[:-1, 3], x[:-1, 4]], axis=1)
    mean, latent = ExactPredictor(model).predict(gp_in, with_var=True)
    m = model.n_terrains
    noise = np.asarray(model.noise, dtype=np.float64).reshape(m, 2)
    var = latent.reshape(n, m, 2) + noise[None] + np.asarray(extra_var, dtype=np.float64)[None, None]
    return Transitions(y, mean.reshape(n, m, 2), var, list(terrains))


def step_loglik(tr: Transitions) -> np.ndarray:
    """(n, M) Gaussian log-likelihood of each step's residual under each terrain (v and omega together)."""
    r = tr.y[:, None, :] - tr.mean
    return -0.5 * np.sum(np.log(2 * np.pi * tr.var) + r * r / tr.var, axis=2)


def step_sq_error(tr: Transitions, noise_var: np.ndarray) -> np.ndarray:
    """(n, M) the paper's per-step fit: squared error of each terrain's mean, in units of one noise per output."""
    r = tr.y[:, None, :] - tr.mean
    return np.sum(r * r / np.asarray(noise_var)[None, None, :], axis=2)


def window_sums(a: np.ndarray, w: int) -> np.ndarray:
    """Sums of `a` (n, ...) over the sliding windows of w consecutive rows: (n - w + 1, ...)."""
    c = np.cumsum(np.concatenate([np.zeros((1,) + a.shape[1:]), a], axis=0), axis=0)
    return c[w:] - c[:-w]


def _same_terrain_windows(terrain: list[str], w: int) -> np.ndarray:
    """Index of the start of each window of w steps that lies on one terrain."""
    codes = np.unique(np.asarray(terrain), return_inverse=True)[1]
    change = np.concatenate([[0], np.cumsum(codes[1:] != codes[:-1])])
    starts = np.arange(len(terrain) - w + 1)
    return starts[change[starts] == change[starts + w - 1]] if starts.size else starts


def confusion(
    score: np.ndarray, terrain: list[str], names: list[str], w: int, largest: bool = True,
    labels: list[str] | None = None,
) -> np.ndarray:
    """(M, M) counts of windows of w steps on one known terrain (row) by the terrain whose summed score wins (column).

    `largest`: the winner has the largest sum (log-likelihood); otherwise the smallest (squared error). `labels`
    (default the terrains) mark where windows must not cross.
    """
    index = {n: i for i, n in enumerate(names)}
    out = np.zeros((len(names), len(names)), dtype=np.int64)
    if len(terrain) < w:
        return out
    sums = window_sums(score, w)
    for s in _same_terrain_windows(labels or terrain, w):
        t = terrain[s]
        if t in index:
            pick = int(np.argmax(sums[s]) if largest else np.argmin(sums[s]))
            out[index[t], pick] += 1
    return out


def separability(
    tr: Transitions, names: list[str], windows: tuple[int, ...] = (1, 10, 20, 50, 100),
    command_change: np.ndarray | None = None,
) -> dict:
    """The numbers of the module docstring, per (true terrain, other terrain) pair and per window length.

    With `command_change` (n, 2), the change of command since the previous step, the calibration of each terrain
    also holds the correlation of its residual with it and the least-squares gain on it.
    """
    ll = step_loglik(tr)
    noise = np.asarray([tr.var[:, :, 0].min(), tr.var[:, :, 1].min()])  # stands in for the paper's unit
    index = {n: i for i, n in enumerate(names)}
    terr = np.asarray(tr.terrain)
    labels = tr.labels()
    pairs: dict = {}
    calibration: dict = {}
    for t in names:
        on = terr == t
        if not on.any():
            continue
        i = index[t]
        z = (tr.y[on] - tr.mean[on, i]) / np.sqrt(tr.var[on, i])
        calibration[t] = {"steps": int(on.sum()), "z2_v": float(np.mean(z[:, 0] ** 2)),
                          "z2_omega": float(np.mean(z[:, 1] ** 2)),
                          "residual_std": [float(s) for s in np.std(tr.y[on] - tr.mean[on, i], axis=0)],
                          "predicted_std": [float(s) for s in np.sqrt(np.mean(tr.var[on, i], axis=0))]}
        if command_change is not None:
            e = tr.y[on] - tr.mean[on, i]
            du = np.asarray(command_change, dtype=np.float64)[on]
            gain = np.sum(du * e, axis=0) / np.maximum(np.sum(du * du, axis=0), 1e-12)
            calibration[t]["command_change_corr"] = [float(np.corrcoef(du[:, k], e[:, k])[0, 1]) for k in range(2)]
            calibration[t]["command_change_gain"] = [float(g) for g in gain]
            calibration[t]["residual_std_after_gain"] = [float(x) for x in np.std(e - gain * du, axis=0)]
        for j, other in enumerate(names):
            if j == i:
                continue
            d = np.abs(tr.mean[on, i] - tr.mean[on, j]) / np.sqrt(tr.var[on, i])
            llr = ll[on, i] - ll[on, j]
            wins = {}
            for w in windows:
                starts = [s for s in _same_terrain_windows(labels, w) if tr.terrain[s] == t]
                if starts:
                    sums = window_sums(ll[:, i] - ll[:, j], w)[starts]
                    wins[w] = float(np.mean(sums > 0))
            pairs[f"{t}|{other}"] = {
                "dprime_v_median": float(np.median(d[:, 0])), "dprime_omega_median": float(np.median(d[:, 1])),
                "dprime_median": float(np.median(np.hypot(d[:, 0], d[:, 1]))),
                "llr_per_step_mean": float(np.mean(llr)), "llr_per_step_std": float(np.std(llr)),
                "true_wins_fraction": wins,
            }
    sq = step_sq_error(tr, noise)
    return {
        "pairs": pairs,
        "calibration": calibration,
        "confusion_loglik": {w: confusion(ll, tr.terrain, names, w, labels=labels).tolist() for w in windows},
        "confusion_sq_error": {w: confusion(sq, tr.terrain, names, w, False, labels).tolist() for w in windows},
    }


def replay(estimator: EstimatorLike, states: np.ndarray, commands: np.ndarray) -> np.ndarray:
    """Feed recorded steps to a terrain estimator as the closed loop does; (T, M) the weights after each step.

    Row k holds the weights the plan of cycle k would have used: the estimate after observing steps 0..k-1 (row 0
    the estimator's starting weights), so the rows line up with a `Trajectory`'s weights and terrains.
    """
    return replay_named(estimator, states, commands)[0]


def replay_named(estimator: EstimatorLike, states: np.ndarray,
                 commands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`replay`'s weights (T, M) and, per row, whether they named a top ground (T,) (`TerrainEstimate.identified`:
    `weight_switches_per_min` counts a change only between rows that name one)."""
    x = np.asarray(states, dtype=np.float64)
    u = np.asarray(commands, dtype=np.float64)
    rows = [estimator.weights]
    named = [bool(getattr(estimator, "identified", True))]
    for k in range(1, u.shape[0]):
        estimator.observe(x[k - 1], u[k - 1], x[k])
        e = estimator.estimate()
        rows.append(np.asarray(e.weights, dtype=np.float64))
        named.append(e.identified)
    return np.asarray(rows), np.asarray(named, dtype=bool)


def switch_response(times: np.ndarray, weights: np.ndarray, terrains: list[str], names: list[str],
                    level: float = 0.5) -> list[dict]:
    """Per change of the ground in a run: how long until the new terrain's weight first exceeds `level`.

    `times` (T+1,), `weights` (T, M) and `terrains` (T,) as in a `Trajectory`. `seconds` is None when it never did
    (before the next change or the run's end) or the new terrain is not one of `names`.
    """
    out = []
    t = np.asarray(times, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    changes = [k for k in range(1, len(terrains)) if terrains[k] != terrains[k - 1]]
    for n, k in enumerate(changes):
        new = terrains[k]
        end = changes[n + 1] if n + 1 < len(changes) else len(terrains)
        seconds = None
        if new in names:
            above = np.nonzero(w[k:end, names.index(new)] > level)[0]
            seconds = float(t[k + above[0]] - t[k]) if above.size else None
        out.append({"at_s": float(t[k]), "from": terrains[k - 1], "to": new, "seconds": seconds})
    return out


def calibrated(
    tr: Transitions, command_change: np.ndarray, names: list[str], gains: np.ndarray | None = None
) -> Transitions:
    """The steps with the noise model made honest, knowing the true terrain (the best case for telling them apart).

    The part of the residual that follows the change of command since the previous step (`command_change` (n, 2))
    goes into the predictions: with `gains` (M, 2) each terrain's own (`m_i + g_i du`, as the Bayesian estimator
    predicts), otherwise one gain per output fitted by least squares on the true terrain's residual and removed
    from the residual. Every terrain's predictive variance is then replaced by the terrains' mean plus the spread
    the true terrain's prediction leaves unexplained, so that the mean z² under the true terrain is about 1 and the
    terrains differ only in what they predict.
    """
    index = np.array([names.index(t) for t in tr.terrain])
    rows = np.arange(len(index))
    du = np.asarray(command_change, dtype=np.float64)
    if gains is not None:
        y, mean = tr.y, tr.mean + np.asarray(gains, dtype=np.float64)[None] * du[:, None, :]
    else:
        e = tr.y - tr.mean[rows, index]
        gain = np.sum(du * e, axis=0) / np.maximum(np.sum(du * du, axis=0), 1e-12)
        y, mean = tr.y - gain * du, tr.mean
    e = y - mean[rows, index]
    shared = tr.var.mean(axis=1)  # (n, 2)
    extra = np.maximum(np.mean(e ** 2, axis=0) - np.mean(shared, axis=0), 0.0)
    var = np.broadcast_to((shared + extra)[:, None, :], tr.var.shape).copy()
    return Transitions(y, mean, var, tr.terrain, tr.segment)


def top_changes(times: np.ndarray, weights: np.ndarray, after_s: float = 3.0,
                identified: np.ndarray | None = None) -> int:
    """How many times the top-weight terrain changes at cycles starting at or after `after_s` (the settling time
    `true_weight_mean` leaves out; `weight_switches_per_min` counts from the start, so the first change from the
    uniform start, where the tie goes to the first terrain, counts there). `identified` (T,) (None: every row): a
    change counts only between rows that name a top, as in `weight_switches_per_min`."""
    t = np.asarray(times, dtype=np.float64)[:-1]
    top = np.argmax(np.asarray(weights, dtype=np.float64), axis=1)
    rows = np.arange(top.size) if identified is None else np.flatnonzero(np.asarray(identified, dtype=bool))
    changed = rows[1:][top[rows[1:]] != top[rows[:-1]]]
    return int(np.count_nonzero(t[changed] >= t[0] + after_s))



def pooled_separability(
    model: GPModel, runs: dict[str, tuple[np.ndarray, np.ndarray, list[str]]], windows: tuple[int, ...],
) -> dict:
    """`separability` of recorded runs pooled per scenario and over all: `runs` maps "scenario/terrain" to (measured
    states (T+1, 5), commands (T, 2), the terrain per step). A run's windows never straddle into the next (its
    terrain label carries the run); runs on a terrain the model does not know are left out.

    Three views, each {scope: separability} with the scopes "all" and each scenario in sorted order:
    `separability` (the GP's variance as trained), `separability_calibrated` (one command-change gain for all
    terrains removed, spread fitted: `calibrated`) and `separability_terrain_gains` (each terrain's profile gain in
    its prediction, spread fitted). Empty when no run is on a known terrain.
    """
    names = list(model.terrains)
    gains = profile_calibration(EstimatorConfig(response="none"), model)[0]  # the robot profile's gains
    parts = []
    for key, (states, commands, terr) in runs.items():
        tr = transitions(model, states, commands, terr)
        du = np.diff(commands, axis=0, prepend=commands[:1])
        parts.append((key, tr, du, all(t in names for t in terr)))
    result: dict = {}
    for s_name in sorted({k.split("/")[0] for k in runs} | {"all"}):
        sel = [(tr, du) for k, tr, du, ok in parts if ok and (s_name == "all" or k.startswith(s_name + "/"))]
        if not sel:
            continue
        pooled = Transitions(np.concatenate([p.y for p, _ in sel]), np.concatenate([p.mean for p, _ in sel]),
                             np.concatenate([p.var for p, _ in sel]), sum((p.terrain for p, _ in sel), []),
                             np.concatenate([np.full(len(p.terrain), i) for i, (p, _) in enumerate(sel)]))
        du_all = np.concatenate([du for _, du in sel])
        result.setdefault("separability", {})[s_name] = separability(pooled, names, windows, du_all)
        result.setdefault("separability_calibrated", {})[s_name] = separability(
            calibrated(pooled, du_all, names), names, windows)
        result.setdefault("separability_terrain_gains", {})[s_name] = separability(
            calibrated(pooled, du_all, names, gains), names, windows)
    return result
