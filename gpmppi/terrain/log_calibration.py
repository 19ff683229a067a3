"""The terrain estimator's calibration fitted from a robot's logs alone: no simulator, no special drives.

`gpmppi.terrain.calibration` fits the per-ground command-change gains and velocity responses by driving our physics
plant (each command of a grid held from rest). A user's robot exists only as logs: per 0.1 s tick the measured state,
the command and the ground's label (`gpmppi dataset` writes them, `tools.dataset.read_dataset` reads them into
`TerrainRun`s). `calibrate_from_runs` fits the same `TerrainCalibration` from those:

- gains: `fit_command_gain` (already log-based) over every run of a ground, pooled as one least-squares fit;
- steady map: the log's held commands (a command kept unchanged for `min_hold_s` or more, as the excitation's
  "hold" segments and a robot driven by hand both have) whose velocities settled; the measured velocity averaged
  over each hold's tail after `settle_s` is one scattered sample of the map. The map on a grid (`LOG_V_REF` x
  `LOG_OMEGA_REF`, the shipped response's at half its spacing) is a smoothing thin-plate-spline fit to those samples,
  with their left-right mirror images (a skid-steer base turns alike both ways) and the stop under a zero command,
  in coordinates where the base's wheel-speed clamp (found by cross-validation) does not bend it. Compared with the
  plant-fitted map in docs/terrain_identification.md ("Calibration from logs");
- rate: the pooled least-squares one-step rate of approach to that map (`fit_rate`'s model) on every step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.interpolate import RBFInterpolator

from gpmppi.gp.model_file import GPModel
from gpmppi.plant.excitation import TerrainRun
from gpmppi.profile.novelty_calibration import NoveltyCalibration
from gpmppi.profile.response import TerrainResponse
from gpmppi.profile.terrain_calibration import CalibrationDataError, TerrainCalibration
from gpmppi.terrain.calibration import fit_command_gain

MIN_HOLD_S = 2.0  # a command kept unchanged this long [s] is a candidate hold
SETTLE_S = 1.6  # the head of a hold left out while the velocities settle [s]
MAX_DRIFT = (0.03, 0.06)  # settled: the tail's two halves differ by at most this (v [m/s], omega [rad/s])
COMMAND_TOL = 1e-4  # commands within this of each other (m/s, rad/s) are the same held command
MIN_HOLDS = 12  # settled holds a ground needs
MIN_V_SPAN = 1.0  # ... spanning v_ref over at least this [m/s]
MIN_OMEGA = 1.0  # ... and reaching |omega_ref| of at least this [rad/s]
# smoothing of the thin-plate-spline fit (on commands scaled to about [0, 1] x [-1, 1]); measured on the Jackal
# against the plant-fitted map (docs/terrain_identification.md, "Calibration from logs")
SMOOTHING = 1e-4
EXTRAPOLATION_MARGIN = 0.05  # the fitted map is kept within the measured velocities' range widened by this share
# the candidates of the command mapping's half track [m] (track x skid-steer multiplier / 2) and wheel-speed limit
# [m/s] (`fit_wheel_limit`)
WHEEL_HALF_TRACKS = np.round(np.arange(0.10, 0.501, 0.04), 3)
WHEEL_LIMITS = np.round(np.arange(1.0, 3.01, 0.1), 2)
# the grid the map is written on: the shipped response's (gpmppi.terrain.calibration.RESPONSE_V_REF, _OMEGA_REF)
# at half its spacing. The estimator reads it bilinearly, and where a wheel setpoint reaches its clamp the map bends
# within less than a 0.2 m/s cell: on the 45 kg robot (docs/robots/heavy_wide.yaml, clamp 1.6 m/s) at its circle
# lane's command (1.485 m/s, 0.217 rad/s) the 0.2 grid read gravel's steady omega as 0.152 rad/s against the plant's
# 0.194 and wet concrete's as 0.170 against 0.212; the 0.1 grid reads 0.185 and 0.211
LOG_V_REF = np.round(np.arange(0.0, 2.0 + 1e-9, 0.1), 4)  # [m/s]
LOG_OMEGA_REF = np.round(np.arange(-3.2, 3.2 + 1e-9, 0.1), 4) + 0.0  # [rad/s] (no -0.0)
NOVELTY_MAX_STEPS = 6000  # steps of each ground's log the novelty calibration replays (10 min of driving)
_SCALE = np.array([2.0, 3.2])  # m/s, rad/s: the response grid's extent, so both inputs weigh alike in the fit


@dataclass(frozen=True)
class Hold:
    """One held command of a log and the velocity it settled at."""

    command: np.ndarray  # (2,) v_ref [m/s], omega_ref [rad/s]
    steady: np.ndarray  # (2,) mean measured v [m/s], omega [rad/s] over the settled tail
    seconds: float  # how long the command was held [s]


def held_segments(commands: np.ndarray, dt: float, min_hold_s: float = MIN_HOLD_S,
                  tol: float = COMMAND_TOL) -> list[tuple[int, int]]:
    """[start, end) tick ranges over which `commands` (T, 2) stay within `tol` of their first, `min_hold_s` or
    longer."""
    u = np.asarray(commands, dtype=np.float64).reshape(-1, 2)
    out = []
    start = 0
    for k in range(1, len(u) + 1):
        if k < len(u) and np.all(np.abs(u[k] - u[start]) <= tol):
            continue
        if (k - start) * dt >= min_hold_s - 1e-9:
            out.append((start, k))
        start = k
    return out


def settled_holds(run: TerrainRun, min_hold_s: float = MIN_HOLD_S, settle_s: float = SETTLE_S,
                  max_drift: Sequence[float] = MAX_DRIFT) -> list[Hold]:
    """The holds of one run whose measured velocities settled: averaged over the hold's tail after `settle_s`, the
    tail's first and second halves within `max_drift` of each other.

    command[k] is applied over [t_k, t_k+1), so a hold over ticks [s, e) shapes the states s+1 .. e.
    """
    n = len(run.state)
    settle = int(round(settle_s / run.dt))
    out = []
    for s, e in held_segments(run.command, run.dt, min_hold_s):
        tail = run.state[s + settle: min(e, n - 1) + 1, 3:5]
        if len(tail) < 4:
            continue
        half = len(tail) // 2
        if np.any(np.abs(tail[:half].mean(axis=0) - tail[half:].mean(axis=0)) > np.asarray(max_drift)):
            continue
        out.append(Hold(run.command[s].astype(np.float64), tail.mean(axis=0), (e - s) * run.dt))
    return out


def _check_holds(terrain: str, holds: list[Hold], min_hold_s: float) -> None:
    """CalibrationDataError unless `holds` are enough, and spread enough, to fit a steady map."""
    u = np.array([h.command for h in holds]).reshape(-1, 2)
    v_span = float(np.ptp(u[:, 0])) if len(u) else 0.0
    w_top = float(np.max(np.abs(u[:, 1]))) if len(u) else 0.0
    if len(holds) >= MIN_HOLDS and v_span >= MIN_V_SPAN and w_top >= MIN_OMEGA:
        return
    found = (f"found v_ref over {v_span:.2f} m/s, |omega_ref| up to {w_top:.2f} rad/s" if len(u) else "found none")
    raise CalibrationDataError(
        f"ground {terrain!r}: {len(holds)} usable held commands (kept >= {min_hold_s:g} s, velocities settled), "
        f"{MIN_HOLDS} needed, spanning v_ref over >= {MIN_V_SPAN:g} m/s and reaching |omega_ref| >= {MIN_OMEGA:g} "
        f"rad/s ({found}); drive it more: hold commands for >= {min_hold_s + 1:g} s at speeds 0-2 m/s and turn rates "
        "-3..3 rad/s, both ways")


def wheel_limited(commands: np.ndarray, half_track: float, wheel_max: float) -> np.ndarray:
    """(N, 2) the commands as a skid-steer base's command mapping passes them on: wheel-speed setpoints
    `v -+ omega half_track`, each clamped to +-`wheel_max` [m/s], mapped back to (v, omega). Past the clamp the steady
    map bends sharply; in these coordinates it is smooth, so a smooth fit holds up to the clamp."""
    u = np.asarray(commands, dtype=np.float64).reshape(-1, 2)
    left = np.clip(u[:, 0] - u[:, 1] * half_track, -wheel_max, wheel_max)
    right = np.clip(u[:, 0] + u[:, 1] * half_track, -wheel_max, wheel_max)
    return np.column_stack([0.5 * (left + right), (right - left) / (2.0 * half_track)])


def _samples(holds: Sequence[Hold], mirror: bool) -> tuple[np.ndarray, np.ndarray]:
    """(commands (K, 2), steady (K, 2)): one sample per distinct command, with the mirror images and the stop."""
    u = np.array([h.command for h in holds], dtype=np.float64).reshape(-1, 2)
    s = np.array([h.steady for h in holds], dtype=np.float64).reshape(-1, 2)
    if mirror:
        u = np.vstack([u, u * [1.0, -1.0], [[0.0, 0.0]]])
        s = np.vstack([s, s * [1.0, -1.0], [[0.0, 0.0]]])
    # one sample per distinct command (the images of omega_ref = 0 and repeated holds would make the system singular)
    key, inverse = np.unique(np.round(u, 6), axis=0, return_inverse=True)
    mean = np.zeros((len(key), 2))
    np.add.at(mean, inverse.reshape(-1), s)
    return key, mean / np.bincount(inverse.reshape(-1))[:, None]


def _fit(holds: Sequence[Hold], smoothing: float, mirror: bool, limit: tuple[float, float] | None):
    """The smoothing thin-plate spline of the holds' steady velocities: a function of commands (N, 2) -> (N, 2)."""
    u, s = _samples(holds, mirror)
    x = u if limit is None else wheel_limited(u, *limit)
    rbf = RBFInterpolator(x / _SCALE, s, kernel="thin_plate_spline", smoothing=smoothing, degree=1)
    lo, hi = s.min(axis=0), s.max(axis=0)
    margin = EXTRAPOLATION_MARGIN * (hi - lo)

    def at(commands: np.ndarray) -> np.ndarray:
        c = np.asarray(commands, dtype=np.float64).reshape(-1, 2)
        c = c if limit is None else wheel_limited(c, *limit)
        # far from the data (a corner no hold reached) the linear tail runs off: no steady velocity beyond what the
        # log measured, with a margin of EXTRAPOLATION_MARGIN of its range
        return np.clip(rbf(c / _SCALE), lo - margin, hi + margin)

    return at


def fit_wheel_limit(holds_by_ground: dict[str, list[Hold]], smoothing: float = SMOOTHING, folds: int = 4,
                    seed: int = 0) -> tuple[float, float] | None:
    """The robot's command mapping (half track [m], wheel-speed limit [m/s]) that best predicts held-out holds, by
    `folds`-fold cross-validation of the steady-map fit pooled over the grounds (the limit is the robot's, not the
    ground's); None when no clamp predicts better than none (no wheel limit inside the logged commands)."""
    rng = np.random.default_rng(seed)
    split = {t: rng.permutation(len(h)) % folds for t, h in holds_by_ground.items()}

    def cv_error(limit: tuple[float, float] | None) -> float:
        err = 0.0
        for t, holds in holds_by_ground.items():
            u = np.array([h.command for h in holds])
            s = np.array([h.steady for h in holds])
            for f in range(folds):
                test = split[t] == f
                train = [h for h, k in zip(holds, ~test, strict=True) if k]
                err += float(np.sum((_fit(train, smoothing, True, limit)(u[test]) - s[test]) ** 2))
        return err

    best, best_err = None, cv_error(None)
    for half_track in WHEEL_HALF_TRACKS:
        for wheel_max in WHEEL_LIMITS:
            e = cv_error((float(half_track), float(wheel_max)))
            if e < best_err:
                best, best_err = (float(half_track), float(wheel_max)), e
    return best


def fit_steady_map(holds: list[Hold], v_ref: np.ndarray = LOG_V_REF, omega_ref: np.ndarray = LOG_OMEGA_REF,
                   smoothing: float = SMOOTHING, mirror: bool = True,
                   limit: tuple[float, float] | None = None) -> np.ndarray:
    """(A, B, 2) the steady (v, omega) on the grid from scattered held commands: a smoothing thin-plate spline per
    output (degree-1 polynomial tail, so it extrapolates linearly past the data, within the measured range).

    `mirror`: add each hold's left-right image (v_ref, -omega_ref) -> (v, -omega), and the stop under a zero
    command; a skid-steer base is built symmetric, and the images halve the noise and fill the other turn.
    `limit`: (half track [m], wheel-speed limit [m/s]) of the base's command mapping (`fit_wheel_limit`): the fit is
    made in `wheel_limited` coordinates, where the map does not bend at the clamp.
    """
    grid = np.stack(np.meshgrid(v_ref, omega_ref, indexing="ij"), axis=-1).reshape(-1, 2)
    return _fit(holds, smoothing, mirror, limit)(grid).reshape(len(v_ref), len(omega_ref), 2)


def fit_rate_runs(steady_at, runs: Sequence[TerrainRun]) -> np.ndarray:
    """(2,) the one-step rate of `v_{k+1} - v_k = rate (S(u_k) - v_k)` (`calibration.fit_rate`'s model), one
    least-squares fit pooled over every step of `runs`; clipped to (0, 1]."""
    num = np.zeros(2)
    den = np.zeros(2)
    for run in runs:
        x = np.asarray(run.state, dtype=np.float64)[:, 3:5]
        u = np.asarray(run.command, dtype=np.float64)[: len(x) - 1]
        if len(u) == 0:
            continue
        gap = np.array([steady_at(c) for c in u]) - x[:-1]
        num += np.sum((x[1:] - x[:-1]) * gap, axis=0)
        den += np.sum(gap * gap, axis=0)
    return np.clip(num / np.maximum(den, 1e-12), 1e-3, 1.0)


def fit_gain_runs(model: GPModel, runs: Sequence[TerrainRun], terrain: str) -> np.ndarray:
    """(2,) `fit_command_gain` pooled over `runs`: each run's gain weighted by its sum of squared command changes
    (the same as one least-squares fit over every step)."""
    num = np.zeros(2)
    den = np.zeros(2)
    for run in runs:
        if len(run.command) < 3:
            continue
        u = np.asarray(run.command, dtype=np.float64)[:-1]  # the last command has no next state
        du = np.diff(u, axis=0, prepend=u[:1])
        weight = np.sum(du * du, axis=0)
        num += fit_command_gain(model, run.state, u, terrain) * weight
        den += weight
    return np.where(den > 1e-12, num / np.maximum(den, 1e-12), 0.0)


def calibration_holds(runs: dict[str, list[TerrainRun]], names: Sequence[str], min_hold_s: float = MIN_HOLD_S,
                      settle_s: float = SETTLE_S) -> dict[str, list[Hold]]:
    """Each ground's settled held commands, the steady map's data; CalibrationDataError naming a ground the runs
    lack, or one with too few holds (and what to drive). Cheap: `gpmppi train` asks it before the GP's minutes of
    fitting, so a log that cannot calibrate is refused at once."""
    missing = [t for t in names if not runs.get(t)]
    if missing:
        raise CalibrationDataError(f"ground(s) {missing} of the GP model have no runs in the log (it has "
                                   f"{sorted(runs)}); calibrate from the log the model was trained on")
    holds = {t: [h for run in runs[t] for h in settled_holds(run, min_hold_s, settle_s)] for t in names}
    for terrain in names:
        _check_holds(terrain, holds[terrain], min_hold_s)
    return holds


def calibrate_from_runs(
    model: GPModel, runs: dict[str, list[TerrainRun]], min_hold_s: float = MIN_HOLD_S, settle_s: float = SETTLE_S,
    smoothing: float = SMOOTHING, wheel_limit: tuple[float, float] | None | str = "fit",
) -> TerrainCalibration:
    """The terrain estimator's calibration of every ground of `model` from its logged runs (`read_dataset`'s form).

    `wheel_limit`: the base's command mapping for the steady map's fit (`fit_steady_map`'s `limit`); "fit": found
    from the holds (`fit_wheel_limit`). Raises CalibrationDataError naming a ground the runs lack, or one with too
    few settled held commands (and what to drive).
    """
    names = list(model.terrains)
    holds = calibration_holds(runs, names, min_hold_s, settle_s)
    gains = np.zeros((len(names), 2))
    steady = np.zeros((len(names), len(LOG_V_REF), len(LOG_OMEGA_REF), 2))
    rates = np.zeros((len(names), 2))
    limit = fit_wheel_limit(holds, smoothing) if wheel_limit == "fit" else wheel_limit
    for m, terrain in enumerate(names):
        steady[m] = fit_steady_map(holds[terrain], smoothing=smoothing, limit=limit)
        one = TerrainResponse(LOG_V_REF, LOG_OMEGA_REF, (terrain,), steady[m:m + 1], np.ones((1, 2)))
        rates[m] = fit_rate_runs(lambda c, one=one: one.steady_at(c)[0], runs[terrain])
        gains[m] = fit_gain_runs(model, runs[terrain], terrain)
    response = TerrainResponse(LOG_V_REF, LOG_OMEGA_REF, tuple(names), steady, rates)
    return TerrainCalibration(tuple(names), gains, response)


def novelty_from_runs(model: GPModel, runs: dict[str, list[TerrainRun]],
                      max_steps: int = NOVELTY_MAX_STEPS) -> NoveltyCalibration:
    """The novelty test's calibration (gpmppi.terrain.novelty.calibrate, and its free-run channel's,
    gpmppi.terrain.free_run.calibrate_free_run) from the logged runs of the grounds of `model`, whose terrain
    calibration must be set: each run replayed through the terrain filter as the service runs it, the residuals under
    every ground of the steps the filter scores and every ground's free-run errors collected, and both channels
    calibrated on the ground each run drove on. The GP conditions on a few hundred clustered inputs of the thousands a
    log holds, so nearly every step is out of its sample. At most `max_steps` steps of each ground are replayed (the
    replay costs ~2 ms a step)."""
    from gpmppi.terrain.estimator import BayesTerrainEstimator
    from gpmppi.terrain.free_run import calibrate_free_run
    from gpmppi.terrain.novelty import calibrate
    from gpmppi.terrain.settings import EstimatorConfig

    names = list(model.terrains)
    known, known_free = [], []
    for terrain in names:
        left = max_steps
        for run in runs.get(terrain, []):
            if left <= 0:
                break
            est = BayesTerrainEstimator(model, EstimatorConfig())
            assert est.novelty is not None
            est.novelty.recorded = []
            if est.free_run is not None:
                est.free_run.recorded = []
            steps = min(len(run.command) - 1, left)
            left -= steps
            for k in range(steps):
                est.observe(run.state[k], run.command[k], run.state[k + 1])
            if est.novelty.recorded:
                known.append((np.array(est.novelty.recorded), names.index(terrain)))
            if est.free_run is not None and est.free_run.recorded:
                known_free.append((np.array(est.free_run.recorded), names.index(terrain)))
    source = f"fitted on the logs of {names}"
    one_step = calibrate(known, source=source)
    free_run = calibrate_free_run(known_free, source=source) if known_free else None
    return replace(one_step, free_run=free_run)
