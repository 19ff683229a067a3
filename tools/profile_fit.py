"""What `gpmppi train` adds to the GP to make a robot profile: the logged runs (the terrain calibration fitted on
them is gpmppi.terrain.log_calibration) and the command line that made it."""

from __future__ import annotations

import shlex

import numpy as np

from gpmppi.plant.excitation import TerrainRun


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


def train_command(data: list[str], output: str, robot: str, terrain: list[str] | None, points: int,
                  iters: int, seed: int, holdout: float | None) -> str:
    """The `gpmppi train` command line that makes a profile, for its `made_by` metadata."""
    args = [*data, "-o", output, "--robot", robot, *[a for t in terrain or [] for a in ("--terrain", t)],
            "--points", str(points), "--iters", str(iters), "--seed", str(seed)]
    if holdout is not None:
        args += ["--holdout", f"{holdout:g}"]
    return "gpmppi train " + shlex.join(args)
