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


def _held(command: np.ndarray, dt: float, hold_s: float) -> int:
    """Runs of one unchanged command lasting `hold_s` or longer."""
    changed = np.r_[True, np.any(np.abs(np.diff(command, axis=0)) > 1e-6, axis=1)]
    lengths = np.diff(np.r_[np.flatnonzero(changed), len(command)])
    return int(np.sum(lengths * dt >= hold_s - 1e-9))


def _calibrate_placeholder(model: GPModel, runs: dict[str, list[TerrainRun]]) -> TerrainCalibration:
    """PLACEHOLDER for `gpmppi.terrain.log_calibration.calibrate_from_runs` (same signature; the lead swaps the one
    call in tools/train.py when merging): the gains fitted on the logs (`fit_command_gain`), the response taken from
    the shipped, plant-fitted gpmppi/data/terrain_response.yaml. Raises CalibrationDataError for a ground without
    enough held commands, as the real fit does."""
    from gpmppi.terrain.calibration import fit_command_gain
    from gpmppi.terrain.response import load_response

    names = list(model.terrains)
    gains = np.zeros((len(names), 2))
    for m, terrain in enumerate(names):
        mine = runs.get(terrain, [])
        held = sum(_held(r.command, r.dt, _PLACEHOLDER_HOLD_S) for r in mine)
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
    response = load_response().select(names, source="shipped terrain response (placeholder)")
    return TerrainCalibration(tuple(names), gains, response)


def train_command(data: str, output: str, robot: str, terrain: list[str] | None, points: int, iters: int,
                  seed: int, holdout: float | None) -> str:
    """The `gpmppi train` command line that makes a profile, for its `made_by` metadata."""
    args = [data, "-o", output, "--robot", robot, *[a for t in terrain or [] for a in ("--terrain", t)],
            "--points", str(points), "--iters", str(iters), "--seed", str(seed)]
    if holdout is not None:
        args += ["--holdout", f"{holdout:g}"]
    return "gpmppi train " + shlex.join(args)
