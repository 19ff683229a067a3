"""The terrain estimator's calibration fitted from a robot's logs alone: no simulator, no special drives.

`gpmppi.terrain.calibration` fits the per-ground command-change gains and velocity responses by driving our physics
plant (each command of a grid held from rest). A user's robot exists only as logs: per 0.1 s tick the measured state,
the command and the ground's label (`gpmppi dataset` writes them, `tools.dataset.read_dataset` reads them into
`TerrainRun`s). `calibrate_from_runs` fits the same `TerrainCalibration` from those:

- gains: `fit_command_gain` (already log-based) over every run of a ground, pooled as one least-squares fit;
- steady map: the log's held commands (a command kept unchanged for `min_hold_s` or more, as the excitation's
  "hold" segments and a robot driven by hand both have) whose velocities settled; the measured velocity averaged
  over each hold's tail after `settle_s` is one scattered sample of the map. The map on the response grid
  (`RESPONSE_V_REF` x `RESPONSE_OMEGA_REF`) is a smoothing thin-plate-spline fit to those samples, with their
  left-right mirror images (a skid-steer base turns alike both ways) and the stop under a zero command. Compared
  with the plant-fitted map in docs/terrain_identification.md ("Calibration from logs");
- rate: the pooled least-squares one-step rate of approach to that map (`fit_rate`'s model) on every step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import RBFInterpolator

from gpmppi.gp.model_file import GPModel
from gpmppi.plant.excitation import TerrainRun
from gpmppi.terrain.calibration import RESPONSE_OMEGA_REF, RESPONSE_V_REF, fit_command_gain
from gpmppi.terrain.response import TerrainResponse
from gpmppi.terrain.terrain_calibration import CalibrationDataError, TerrainCalibration

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


def fit_steady_map(holds: list[Hold], v_ref: np.ndarray = RESPONSE_V_REF, omega_ref: np.ndarray = RESPONSE_OMEGA_REF,
                   smoothing: float = SMOOTHING, mirror: bool = True) -> np.ndarray:
    """(A, B, 2) the steady (v, omega) on the grid from scattered held commands: a smoothing thin-plate spline per
    output (degree-1 polynomial tail, so it extrapolates linearly past the data).

    `mirror`: add each hold's left-right image (v_ref, -omega_ref) -> (v, -omega), and the stop under a zero
    command; a skid-steer base is built symmetric, and the images halve the noise and fill the other turn.
    """
    u = np.array([h.command for h in holds], dtype=np.float64).reshape(-1, 2)
    s = np.array([h.steady for h in holds], dtype=np.float64).reshape(-1, 2)
    if mirror:
        u = np.vstack([u, u * [1.0, -1.0], [[0.0, 0.0]]])
        s = np.vstack([s, s * [1.0, -1.0], [[0.0, 0.0]]])
    # one sample per distinct command (the images of omega_ref = 0 and repeated holds would make the system singular)
    key, inverse = np.unique(np.round(u, 6), axis=0, return_inverse=True)
    mean = np.zeros((len(key), 2))
    np.add.at(mean, inverse.reshape(-1), s)
    mean /= np.bincount(inverse.reshape(-1))[:, None]
    fit = RBFInterpolator(key / _SCALE, mean, kernel="thin_plate_spline", smoothing=smoothing, degree=1)
    grid = np.stack(np.meshgrid(v_ref, omega_ref, indexing="ij"), axis=-1).reshape(-1, 2)
    steady = fit(grid / _SCALE).reshape(len(v_ref), len(omega_ref), 2)
    # far from the data (a corner of the grid no hold reached) the linear tail runs off: no steady velocity beyond
    # what the log measured, with a margin of EXTRAPOLATION_MARGIN of its range
    lo, hi = mean.min(axis=0), mean.max(axis=0)
    margin = EXTRAPOLATION_MARGIN * (hi - lo)
    return np.clip(steady, lo - margin, hi + margin)


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


def calibrate_from_runs(
    model: GPModel, runs: dict[str, list[TerrainRun]], min_hold_s: float = MIN_HOLD_S, settle_s: float = SETTLE_S,
    smoothing: float = SMOOTHING,
) -> TerrainCalibration:
    """The terrain estimator's calibration of every ground of `model` from its logged runs (`read_dataset`'s form).

    Raises CalibrationDataError naming a ground the runs lack, or one with too few settled held commands (and what
    to drive).
    """
    names = list(model.terrains)
    missing = [t for t in names if not runs.get(t)]
    if missing:
        raise CalibrationDataError(f"ground(s) {missing} of the GP model have no runs in the log (it has "
                                   f"{sorted(runs)}); calibrate from the log the model was trained on")
    gains = np.zeros((len(names), 2))
    steady = np.zeros((len(names), len(RESPONSE_V_REF), len(RESPONSE_OMEGA_REF), 2))
    rates = np.zeros((len(names), 2))
    for m, terrain in enumerate(names):
        holds = [h for run in runs[terrain] for h in settled_holds(run, min_hold_s, settle_s)]
        _check_holds(terrain, holds, min_hold_s)
        steady[m] = fit_steady_map(holds, smoothing=smoothing)
        one = TerrainResponse(RESPONSE_V_REF, RESPONSE_OMEGA_REF, (terrain,), steady[m:m + 1], np.ones((1, 2)))
        rates[m] = fit_rate_runs(lambda c, one=one: one.steady_at(c)[0], runs[terrain])
        gains[m] = fit_gain_runs(model, runs[terrain], terrain)
    response = TerrainResponse(RESPONSE_V_REF, RESPONSE_OMEGA_REF, tuple(names), steady, rates)
    return TerrainCalibration(tuple(names), gains, response)
