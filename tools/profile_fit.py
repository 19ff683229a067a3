"""What `gpmppi train` adds to the GP to make a robot profile: the logged runs (the terrain calibration fitted on
them is gpmppi.terrain.log_calibration), the calibration-only logs (`--calibration-log`) and the command line that
made it."""

from __future__ import annotations

import shlex
from pathlib import Path

import numpy as np

from gpmppi.plant.excitation import TerrainRun
from tools.log_reader import DataError


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


def check_calibration_data(paths: list[Path], data: list[Path]) -> None:
    """DataError when `--calibration-log`s come with a residual CSV as the training data (no time series, so the
    profile gets no terrain calibration to add them to); asked before anything is read."""
    if paths and any(p.suffix.lower() == ".csv" for p in data):
        raise DataError("--calibration-log needs MCAP training logs: a residual CSV has no time series, so the profile "
                        "gets no terrain calibration to add the calibration logs to")


def calibration_log_runs(paths: list[Path], data: list[Path], grounds: list[str], terrain: list[str] | None,
                         dt: float, robot: str | None) -> dict[str, list[TerrainRun]]:
    """The runs of `gpmppi train --calibration-log` logs, by ground: logs that feed the terrain estimator's
    calibration only, never the GP's or the nominal model's training data. Each is read as a training log is (the
    same labels, robot and `--terrain` rules); its grounds must be among the trained `grounds` (with `--terrain`
    the others are left out, as in the training logs). A DataError of one line names the log
    and what is wrong: a residual CSV as the training data (no time series, so no calibration), a file that is not
    an MCAP log, a log given both as training and calibration log, a ground the GP was not trained on."""
    from tools.train_data import is_mcap, read_log_series

    if not paths:
        return {}
    check_calibration_data(paths, data)
    trained = {p.resolve() for p in data}
    series = []
    for path in paths:
        if path.resolve() in trained:
            raise DataError(f"{path} is given both as a training log and as a --calibration-log; name it once (as a "
                            "training log its data also feeds the calibration)")
        if not is_mcap(path):
            raise DataError(f"{path}: --calibration-log takes an MCAP log (recorded by `gpmppi calibrate drive`, "
                            "`gpmppi launch --record` or `gpmppi dataset`)")
        one = read_log_series(path, dt, terrain[0] if terrain and len(terrain) == 1 else None, robot)
        extra = sorted(set(one) - set(grounds))
        if extra and not terrain:
            raise DataError(f"{path}: calibration log of ground(s) {extra} the training logs lack (they have "
                            f"{grounds}); drive those grounds in a training log too (the GP needs them), or keep only "
                            "the trained ones with --terrain")
        kept = {t: s for t, s in one.items() if t in grounds}
        if not kept:
            raise DataError(f"{path}: calibration log of ground(s) {sorted(one)}, none of them trained ({grounds})")
        series.append(kept)
    runs: dict[str, list[TerrainRun]] = {}
    for one in series:  # each log's own runs: no one-step pair spans two logs
        for t, r in runs_from_series(one, dt).items():
            runs.setdefault(t, []).extend(r)
    return runs


def train_command(data: list[str], output: str, robot: str, terrain: list[str] | None, points: int,
                  iters: int, seed: int, holdout: float | None, calibration_logs: list[str] | None = None,
                  steady_points: int = 0, fit: str | None = None) -> str:
    """The `gpmppi train` command line that makes a profile, for its `made_by` metadata."""
    args = [*data, "-o", output, "--robot", robot, *[a for t in terrain or [] for a in ("--terrain", t)],
            *[a for c in calibration_logs or [] for a in ("--calibration-log", c)],
            "--points", str(points), "--iters", str(iters), "--seed", str(seed)]
    if holdout is not None:
        args += ["--holdout", f"{holdout:g}"]
    if steady_points:
        args += ["--steady-points", str(steady_points)]
    if fit is not None:  # named always: the default may change, the command must still remake the profile
        args += ["--fit", fit]
    return "gpmppi train " + shlex.join(args)
