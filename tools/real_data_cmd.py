"""`gpmppi evaluate terrain-real-data`: the terrain estimator on the paper's real Jackal residual table.

The paper's `gp_test.csv` holds the same inputs driven on three grounds; windows of random rows of one ground go
through a fresh estimator (only its one-step GP evidence: the table is not a time series; see
`gpmppi.terrain.real_data`), and the weight it ends on the true ground is reported per ground and window length.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from tools.cli_checks import OUT_FILE, fail, write_text_atomic


def real_data_cmd(
    table: Annotated[Path, typer.Argument(help="The paper's residual table (gp_test.csv form).")],
    gp_model: Annotated[Path, typer.Option(
        "--profile", help="Robot profile (its GP) of the robot the table comes from, with its grounds (e.g. "
        "`gpmppi train gp_train.csv ...`).")],
    window: Annotated[list[int] | None, typer.Option(
        "--window", min=1, max=10_000, help="Rows per window (repeat; default 15 and 30).")] = None,
    trials: Annotated[int, typer.Option("--trials", "-n", min=1, max=100_000, help="Windows per ground.")] = 200,
    seed: Annotated[int, typer.Option("--seed", min=0, help="Seed of the row draws.")] = 0,
    estimator: Annotated[list[str] | None, typer.Option(
        "--estimator", help="Estimator setting KEY=VALUE on top of the one-step-only evidence (repeat).")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
    out: Annotated[Path | None, typer.Option("--output", "-o", metavar=OUT_FILE, help="Write the JSON here.")] = None,
) -> None:
    """Weight on the true ground over windows of one ground's rows of the paper's real data (one-step evidence)."""
    from gpmppi.evaluation.runner import cached_gp_model
    from gpmppi.terrain.real_data import ONE_STEP_ONLY, read_residual_table, window_scores
    from gpmppi.terrain.settings import EstimatorConfig
    from tools.terrain_cmd import estimator_settings

    model = cached_gp_model(str(gp_model))
    rows = read_residual_table(table)
    try:
        config = EstimatorConfig(**{**ONE_STEP_ONLY, **dict(estimator_settings(estimator or []))})
    except ValueError as e:
        fail(f"--estimator {e}")
    windows = window or [15, 30]
    result = {"table": str(table), "estimator": config.model_dump(mode="json"), "trials": trials, "seed": seed,
              "windows": {str(w): window_scores(model, rows, w, trials, seed, config) for w in windows}}
    text = json.dumps(result, indent=1)
    if out is not None:
        write_text_atomic(out, text)
    if as_json:
        print(text)
        return
    t = Table("rows", "ground", "true-ground weight (mean ± std)", "true ground on top")
    for w, per in result["windows"].items():
        for ground, s in per.items():
            t.add_row(w, ground, f"{s['true_weight_mean']:.2f} ± {s['true_weight_std']:.2f}",
                      f"{100 * s['top_fraction']:.0f} %")
    Console().print(t)
