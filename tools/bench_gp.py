"""`gpmppi bench gp`: grid vs exact GP predictor, accuracy and predictions per second."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console
from rich.table import Table


def _rate(fn, n_points: int, repeats: int = 3) -> float:
    """Best-of-`repeats` predictions per second (the machine is shared: the best run is the least disturbed)."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return n_points / best


def bench_gp(model_path: Path | None, points: int, seed: int) -> dict:
    from gpmppi.gp.exact import ExactPredictor
    from gpmppi.gp.grid import GridPredictor
    from gpmppi.gp.model_file import DEFAULT_MODEL_PATH, GPModel

    path = model_path or DEFAULT_MODEL_PATH
    model = GPModel.load(path)
    stored = model.has_stored_grid()
    t0 = time.perf_counter()
    grid = GridPredictor(model)  # builds the table when the file does not store one
    grid_setup_s = time.perf_counter() - t0
    exact = ExactPredictor(model)
    x = np.random.default_rng(seed).uniform(model.domain_lo, model.domain_hi, (points, 4))
    exact.predict(x[:10])  # compile / load the numba caches outside the timing
    grid.predict(x[:10])
    em, ev = exact.predict(x)
    gm, gv = grid.predict(x)
    tasks = []
    for t, name in enumerate(model.tasks):
        rms_mean = float(np.sqrt(np.mean(em[:, t] ** 2)))
        rms_var = float(np.sqrt(np.mean(ev[:, t] ** 2)))
        tasks.append({
            "task": name,
            "rms_mean": rms_mean,
            "mean_error_pct": 100.0 * float(np.sqrt(np.mean((gm[:, t] - em[:, t]) ** 2))) / rms_mean,
            "max_mean_error": float(np.max(np.abs(gm[:, t] - em[:, t]))),
            "rms_var": rms_var,
            "var_error_pct": 100.0 * float(np.sqrt(np.mean((gv[:, t] - ev[:, t]) ** 2))) / rms_var,
        })
    return {
        "model": str(path),
        "points": points,
        "grid_nodes": model.grid().nodes,
        "grid_stored": stored,
        "grid_setup_s": grid_setup_s,
        "train_points": int(model.train_x.shape[0]),
        "tasks": tasks,
        "exact_per_s": _rate(lambda: exact.predict(x), points),
        "exact_mean_only_per_s": _rate(lambda: exact.predict(x, with_var=False), points),
        "grid_per_s": _rate(lambda: grid.predict(x), points),
    }


def register(app: typer.Typer) -> None:
    """Add `gpmppi bench gp`."""

    @app.command("gp")
    def bench_gp_cmd(
        model: Annotated[Path | None, typer.Option(help="model file (default: the shipped model)")] = None,
        points: Annotated[int, typer.Option(help="random in-domain inputs")] = 100_000,
        seed: Annotated[int, typer.Option(help="seed of the inputs")] = 0,
        as_json: Annotated[bool, typer.Option("--json", help="print JSON instead of a table")] = False,
    ) -> None:
        """Grid vs exact predictor: RMS mean/variance error (% of RMS) per task and predictions/s."""
        from gpmppi.gp.model_file import ModelFileError

        if points < 1:
            Console(stderr=True, soft_wrap=True).print("[red]error:[/red] --points must be at least 1")
            raise typer.Exit(code=2)
        try:
            r = bench_gp(model, points, seed)
        except ModelFileError as e:
            Console(stderr=True, soft_wrap=True).print(f"[red]error:[/red] {e}", highlight=False)
            raise typer.Exit(code=2) from None
        if as_json:
            typer.echo(json.dumps(r, indent=1))
            return
        console = Console()
        table = Table(title=f"grid ({r['grid_nodes']}^4 nodes) vs exact ({r['train_points']} training inputs), "
                            f"{r['points']} random in-domain inputs")
        for col in ("task", "RMS mean", "mean err % (goal < 1)", "max |mean err|", "RMS var", "var err %"):
            table.add_column(col, justify="right")
        for t in r["tasks"]:
            table.add_row(t["task"], f"{t['rms_mean']:.4g}", f"{t['mean_error_pct']:.3f}",
                          f"{t['max_mean_error']:.3g}", f"{t['rms_var']:.3g}", f"{t['var_error_pct']:.3f}")
        console.print(table)
        console.print(
            f"predictions/s (all {len(r['tasks'])} tasks, mean + variance; shared machine, timings noisy): "
            f"exact {r['exact_per_s']:.3g}, exact mean-only {r['exact_mean_only_per_s']:.3g}, "
            f"grid {r['grid_per_s']:.3g}; grid table {'loaded' if r['grid_stored'] else 'built'} "
            f"in {r['grid_setup_s']:.2f} s"
        )
