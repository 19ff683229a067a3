"""What `gpmppi train` adds to the GP to make a robot profile: the logged runs and the terrain calibration."""

from __future__ import annotations

import shlex

import numpy as np

from gpmppi.gp.model_file import GPModel
from gpmppi.plant.excitation import TerrainRun
from gpmppi.terrain.terrain_calibration import CalibrationDataError, TerrainCalibration

# PLACEHOLDER until the log-based calibration fit lands: a ground needs this many commands held this long
_PLACEHOLDER_HOLD_S = 2.0
_PLACEHOLDER_MIN_HOLDS = 3


def runs_from_series(series: dict[str, dict[str, np.ndarray]], dt: float) -> dict[str, list[TerrainRun]]:
    """`read_log_series`' per-ground series as contiguous runs (one per segment), `read_dataset`'s form."""
    runs: dict[str, list[TerrainRun]] = {}
    for terrain, s in series.items():
        seg = np.asarray(s["seg"])
        state = np.column_stack([np.asarray(s[k], dtype=np.float64) for k in ("x", "y", "yaw", "v", "w")])
        command = np.column_stack([np.asarray(s["v_ref"], dtype=np.float64), np.asarray(s["w_ref"], dtype=np.float64)])
        cuts = np.flatnonzero(np.diff(seg) != 0) + 1
        for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, len(seg)], strict=True):
            if hi - lo >= 2:  # a run of one tick has no transition
                runs.setdefault(terrain, []).append(TerrainRun(
                    terrain, dt, np.arange(hi - lo) * dt, state[lo:hi], command[lo:hi], state[lo:hi].copy()))
    return runs


def _holds(run: TerrainRun, hold_s: float, settle_s: float = 1.2) -> list[tuple[np.ndarray, np.ndarray]]:
    """(command (2,), mean measured (v, omega) after `settle_s`) of each command held `hold_s` or longer."""
    changed = np.r_[True, np.any(np.abs(np.diff(run.command, axis=0)) > 1e-6, axis=1)]
    starts = np.flatnonzero(changed)
    out = []
    for lo, hi in zip(starts, np.r_[starts[1:], len(run.command)], strict=True):
        if (hi - lo) * run.dt >= hold_s - 1e-9:
            out.append((run.command[lo], run.state[lo + int(round(settle_s / run.dt)):hi, 3:5].mean(axis=0)))
    return out


def _placeholder_response(terrain: str, runs: list[TerrainRun], holds: list[tuple[np.ndarray, np.ndarray]]):
    """PLACEHOLDER for a ground the shipped response lacks: the steady map on the response grid as the
    inverse-distance mean of the held commands' settled velocities, and the rate fitted on the runs."""
    from gpmppi.terrain.calibration import RESPONSE_OMEGA_REF, RESPONSE_V_REF, fit_rate
    from gpmppi.terrain.response import TerrainResponse

    u = np.array([h[0] for h in holds])
    y = np.array([h[1] for h in holds])
    grid = np.stack(np.meshgrid(RESPONSE_V_REF, RESPONSE_OMEGA_REF, indexing="ij"), axis=-1)  # (A, B, 2)
    d2 = np.sum(((grid[:, :, None, :] - u[None, None]) / np.array([2.0, 3.2])) ** 2, axis=-1)  # (A, B, H)
    w = 1.0 / (d2 + 1e-3)
    steady = np.einsum("abh,hc->abc", w, y) / w.sum(axis=-1, keepdims=True)
    one = TerrainResponse(RESPONSE_V_REF, RESPONSE_OMEGA_REF, (terrain,), steady[None], np.ones((1, 2)))
    rates = [fit_rate(lambda c: one.steady_at(c)[0], r.state, r.command[:-1]) for r in runs if len(r.command) > 2]
    return steady, np.mean(rates, axis=0)


def _calibrate_placeholder(model: GPModel, runs: dict[str, list[TerrainRun]]) -> TerrainCalibration:
    """PLACEHOLDER for `gpmppi.terrain.log_calibration.calibrate_from_runs` (same signature; the lead swaps the one
    call in tools/train.py when merging): the gains fitted on the logs (`fit_command_gain`), the response taken from
    the shipped, plant-fitted gpmppi/data/terrain_response.yaml (a ground it lacks: `_placeholder_response`).
    Raises CalibrationDataError for a ground without enough held commands, as the real fit does."""
    from gpmppi.terrain.calibration import fit_command_gain
    from gpmppi.terrain.response import TerrainResponse, load_response

    names = list(model.terrains)
    gains = np.zeros((len(names), 2))
    shipped = load_response()
    steady = np.zeros((len(names), len(shipped.v_ref), len(shipped.omega_ref), 2))
    rates = np.zeros((len(names), 2))
    for m, terrain in enumerate(names):
        mine = runs.get(terrain, [])
        holds = [h for r in mine for h in _holds(r, _PLACEHOLDER_HOLD_S)]
        held = len(holds)
        if held < _PLACEHOLDER_MIN_HOLDS:
            raise CalibrationDataError(
                f"ground {terrain!r}: {held} commands held >= {_PLACEHOLDER_HOLD_S:g} s, {_PLACEHOLDER_MIN_HOLDS} "
                "needed for the terrain calibration's steady response; drive it more: hold commands for >= 3 s at "
                "speeds 0-2 m/s and turn rates -3..3 rad/s, both ways")
        num, den = np.zeros(2), np.zeros(2)
        for r in mine:  # the gain of all runs pooled: each run's weighted by its sum of squared command changes
            du = np.diff(r.command[:-1], axis=0, prepend=r.command[:1])
            w = np.sum(du * du, axis=0)
            num += fit_command_gain(model, r.state, r.command[:-1], terrain) * w
            den += w
        gains[m] = np.where(den > 1e-12, num / np.maximum(den, 1e-12), 0.0)
        if terrain in shipped.terrains:
            one = shipped.select([terrain])
            steady[m], rates[m] = one.steady[0], one.rate[0]
        else:
            steady[m], rates[m] = _placeholder_response(terrain, mine, holds)
    response = TerrainResponse(shipped.v_ref, shipped.omega_ref, tuple(names), steady, rates)
    return TerrainCalibration(tuple(names), gains, response)


def train_command(data: list[str], output: str, robot: str, terrain: list[str] | None, points: int,
                  iters: int, seed: int, holdout: float | None) -> str:
    """The `gpmppi train` command line that makes a profile, for its `made_by` metadata."""
    args = [*data, "-o", output, "--robot", robot, *[a for t in terrain or [] for a in ("--terrain", t)],
            "--points", str(points), "--iters", str(iters), "--seed", str(seed)]
    if holdout is not None:
        args += ["--holdout", f"{holdout:g}"]
    return "gpmppi train " + shlex.join(args)
