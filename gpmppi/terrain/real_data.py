"""The terrain estimator on the paper's real Jackal data: how often windows of one ground pick that ground.

The paper's test set (`gp_test.csv`) holds one-step residuals of the same inputs (command and measured velocity)
driven on three grounds: per row the inputs `[v_ref, omega_ref, v, omega]` and, per ground, the measured next
velocity minus the nominal dynamic unicycle's step. It is not a time series (the rows are matched inputs, not
consecutive steps), so of the estimator's evidence only the one-step GP part applies: the command-change term
(which needs the previous command) and the velocity response (which needs a run of steps) are off, and say so.

A window is `window` random rows of one ground, fed to a fresh estimator as if consecutive steps: each row's
state is the measured velocity, its next state that velocity stepped by the nominal model plus the ground's
residual. What is reported per ground is the weight the estimator gives the true ground at the window's end and
how often the true ground is on top.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gpmppi.gp.model_file import GPModel
from gpmppi.models.dynamic_unicycle import velocity_step_exact
from gpmppi.terrain.estimator import make_estimator
from gpmppi.terrain.settings import EstimatorConfig

INPUT_COLUMNS = ("gp_ip_cmd_lin", "gp_ip_cmd_ang", "gp_ip_curr_lin", "gp_ip_curr_ang")
# the evidence a table of unordered one-step rows can carry: no command change, no response
ONE_STEP_ONLY = {"command_change": "none", "response": "none"}


class RealDataError(ValueError):
    """A residual table that is not the paper's form (inputs and per-ground `{Ground}_{Lin,Ang}_Error` columns)."""


@dataclass(frozen=True)
class ResidualTable:
    """Matched one-step rows: the same inputs on every ground, each ground's measured residual."""

    inputs: np.ndarray  # (n, 4) v_ref [m/s], omega_ref [rad/s], measured v [m/s], measured omega [rad/s]
    residuals: dict[str, np.ndarray]  # ground (lower case) -> (n, 2) measured next (v, omega) minus the nominal step


def read_residual_table(path: Path | str) -> ResidualTable:
    """The paper's CSV (see the module docstring); a `RealDataError` naming the file and what is missing."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if len(rows) < 2:
        raise RealDataError(f"{path}: no rows (expected a header and the paper's residual rows)")
    header = rows[0]
    try:
        body = np.array(rows[1:], dtype=np.float64)
    except ValueError as e:
        raise RealDataError(f"{path}: not a table of numbers under one header ({e})") from None
    if body.ndim != 2 or body.shape[1] != len(header) or not np.all(np.isfinite(body)):
        raise RealDataError(f"{path}: every row must hold {len(header)} finite numbers, one per header column")
    missing = [c for c in INPUT_COLUMNS if c not in header]
    grounds = sorted({c[: -len("_Lin_Error")] for c in header if c.endswith("_Lin_Error")})
    if missing or not grounds:
        raise RealDataError(f"{path}: expected columns {list(INPUT_COLUMNS)} and {{Ground}}_Lin_Error, "
                            f"{{Ground}}_Ang_Error per ground; missing {missing or 'every ground column'}")
    inputs = body[:, [header.index(c) for c in INPUT_COLUMNS]]
    residuals = {g.lower(): body[:, [header.index(f"{g}_Lin_Error"), header.index(f"{g}_Ang_Error")]]
                 for g in grounds}
    return ResidualTable(inputs, residuals)


def window_scores(
    model: GPModel, table: ResidualTable, window: int, trials: int, seed: int, config: EstimatorConfig,
) -> dict[str, dict[str, float]]:
    """Per ground of `model` found in `table`: over `trials` windows of `window` random rows of that ground, the
    mean and standard deviation of the estimator's weight on it and the fraction of windows it is on top."""
    if not 1 <= window <= table.inputs.shape[0]:
        raise ValueError(f"window must be 1..{table.inputs.shape[0]} rows, got {window}")
    names = list(model.terrains)
    grounds = [g for g in names if g in table.residuals]
    if not grounds:
        raise RealDataError(f"none of the model's grounds {names} is in the table (has {sorted(table.residuals)})")
    rng = np.random.default_rng(seed)
    u = table.inputs[:, :2]
    v_nom, w_nom = velocity_step_exact(model.theta, table.inputs[:, 2].copy(), table.inputs[:, 3].copy(),
                                       u[:, 0].copy(), u[:, 1].copy(), model.dt)
    out: dict[str, dict[str, float]] = {}
    for ground in grounds:
        truth = names.index(ground)
        next_vw = np.column_stack([v_nom, w_nom]) + table.residuals[ground]
        weights, top = [], []
        for _ in range(trials):
            est = make_estimator(model, config)
            for k in rng.choice(table.inputs.shape[0], size=window, replace=False):
                x = np.array([0.0, 0.0, 0.0, table.inputs[k, 2], table.inputs[k, 3]])
                x1 = np.array([0.0, 0.0, 0.0, next_vw[k, 0], next_vw[k, 1]])
                est.observe(x, u[k], x1)
            w = est.estimate().weights
            weights.append(float(w[truth]))
            top.append(bool(np.argmax(w) == truth))
        out[ground] = {"true_weight_mean": float(np.mean(weights)), "true_weight_std": float(np.std(weights)),
                       "top_fraction": float(np.mean(top))}
    return out
