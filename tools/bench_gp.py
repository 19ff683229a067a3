"""`gpmppi bench gp`: grid vs exact GP predictor, accuracy per task, table sizes and predictions per second."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from tools.cli_checks import fail

INTERPOLATIONS = ("simplex", "multilinear")  # the planner's default first


def _rate(fn, n_points: int, repeats: int = 3) -> float:
    """Best-of-`repeats` predictions per second (the machine is shared: the best run is the least disturbed)."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return n_points / best


def _pct(err: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """RMS of `err` per column as a percentage of the RMS of `ref`."""
    return 100.0 * np.sqrt(np.mean(err**2, axis=0)) / np.sqrt(np.mean(ref**2, axis=0))


def bench_gp(
    model_path: Path | None, points: int, seed: int, spacing: float | None = None, nodes: int | None = None
) -> dict:
    """Grid vs exact on `points` uniform random inputs of the model's domain box.

    `spacing` / `nodes`: rebuild the table (sized from the lengthscales with this spacing, or `nodes`
    on every axis) instead of using the stored one.
    """
    from gpmppi.gp.exact import ExactPredictor
    from gpmppi.gp.grid import GridPredictor
    from gpmppi.gp.grid_table import DEFAULT_SPACING, build_grid
    from gpmppi.gp.model_file import DEFAULT_MODEL_PATH, GPModel

    path = model_path or DEFAULT_MODEL_PATH
    model = GPModel.load(path)
    stored = model.has_stored_grid() and spacing is None and nodes is None
    t0 = time.perf_counter()
    c0 = time.process_time()
    if stored:
        model.grid()
    elif spacing is not None or nodes is not None:
        model.set_grid(build_grid(model, nodes, spacing=spacing or DEFAULT_SPACING))
    else:
        model.grid()  # no stored table: built with the default sizing, as the planner would
    grid_setup_s = time.perf_counter() - t0
    grid_setup_cpu_s = time.process_time() - c0
    g = model.grid()
    predictors = {k: GridPredictor(model, k) for k in INTERPOLATIONS}
    exact = ExactPredictor(model)
    x = np.random.default_rng(seed).uniform(model.domain_lo, model.domain_hi, (points, 4))
    exact.predict(x[:10])  # compile / load the numba caches outside the timing
    for p in predictors.values():
        p.predict(x[:10])
    em, ev = exact.predict(x)
    errors = {}
    for k, p in predictors.items():
        gm, gv = p.predict(x)
        errors[k] = (_pct(gm - em, em), _pct(gv - ev, ev), np.max(np.abs(gm - em), axis=0))
    tasks = []
    for t, name in enumerate(model.tasks):
        row = {
            "task": name,
            "min_lengthscale_axis": int(np.argmin(model.lengthscale[t])),
            "rms_mean": float(np.sqrt(np.mean(em[:, t] ** 2))),
            "rms_var": float(np.sqrt(np.mean(ev[:, t] ** 2))),
        }
        for k, (mean_pct, var_pct, max_err) in errors.items():
            prefix = "" if k == "multilinear" else f"{k}_"
            row[f"{prefix}mean_error_pct"] = float(mean_pct[t])
            row[f"{prefix}var_error_pct"] = float(var_pct[t])
            row[f"{prefix}max_mean_error"] = float(max_err[t])
        tasks.append(row)
    n_nodes = g.n_nodes
    return {
        "model": str(path),
        "points": points,
        "grid_dims": list(g.dims),
        "grid_nodes": g.nodes,
        "grid_n_nodes": n_nodes,
        # what the planner holds: the per-terrain float32 table (rollout order) and the collapsed (nodes, 4) one
        "table_mb": n_nodes * g.table.shape[4] * 4 / 1e6,
        "collapsed_table_mb": n_nodes * 4 * 4 / 1e6,
        "grid_stored": stored,
        "grid_setup_s": grid_setup_s,
        "grid_setup_cpu_s": grid_setup_cpu_s,
        "min_lengthscale": model.lengthscale.min(axis=0).tolist(),
        "spacing_per_lengthscale": ((model.domain_hi - model.domain_lo) / (np.asarray(g.dims) - 1)
                                    / model.lengthscale.min(axis=0)).tolist(),
        "train_points": int(model.train_x.shape[0]),
        "tasks": tasks,
        "exact_per_s": _rate(lambda: exact.predict(x), points),
        "exact_mean_only_per_s": _rate(lambda: exact.predict(x, with_var=False), points),
        "grid_per_s": _rate(lambda: predictors["multilinear"].predict(x), points),
        "simplex_per_s": _rate(lambda: predictors["simplex"].predict(x), points),
    }


def register(app: typer.Typer) -> None:
    """Add `gpmppi bench gp`."""

    @app.command("gp")
    def bench_gp_cmd(
        model: Annotated[Path | None, typer.Option(
            "--profile", help="robot profile (default: the shipped Jackal profile)")] = None,
        points: Annotated[int, typer.Option(
            min=1, max=10_000_000, help="random in-domain inputs")] = 100_000,
        seed: Annotated[int, typer.Option(min=0, help="seed of the inputs")] = 0,
        spacing: Annotated[float | None, typer.Option(
            min=0.001, max=10.0,
            help="rebuild the table with this node spacing (fraction of each axis's smallest lengthscale)")] = None,
        nodes: Annotated[int | None, typer.Option(
            min=2, max=200, help="rebuild the table with this many nodes on every axis")] = None,
        as_json: Annotated[bool, typer.Option("--json", help="print JSON instead of a table")] = False,
    ) -> None:
        """Grid vs exact predictor: RMS mean/variance error (% of RMS) per task, table size and predictions/s."""
        from gpmppi.gp.model_file import ModelFileError

        if spacing is not None and nodes is not None:
            fail("give --spacing or --nodes, not both")
        try:
            r = bench_gp(model, points, seed, spacing, nodes)
        except ModelFileError as e:
            fail(str(e))
        if as_json:
            typer.echo(json.dumps(r, indent=1))
            return
        console = Console(width=max(Console().width, 110))
        dims = "x".join(str(d) for d in r["grid_dims"])
        table = Table(title=f"grid ({dims} nodes) vs exact ({r['train_points']} training inputs), "
                            f"{r['points']} random in-domain inputs; RMS error as % of RMS, goal < 1",
                      caption="simplex: the planner's interpolation (default); multilinear: `gp predict --mode grid`")
        for col in ("task", "RMS mean", "simplex mean %", "multilinear mean %", "max |mean err|", "RMS var",
                    "simplex var %", "multilinear var %"):
            table.add_column(col, justify="right", no_wrap=True)
        for t in r["tasks"]:
            table.add_row(t["task"], f"{t['rms_mean']:.4g}", f"{t['simplex_mean_error_pct']:.3f}",
                          f"{t['mean_error_pct']:.3f}", f"{t['simplex_max_mean_error']:.3g}", f"{t['rms_var']:.3g}",
                          f"{t['simplex_var_error_pct']:.3f}", f"{t['var_error_pct']:.3f}")
        console.print(table)
        spacing_txt = ", ".join(f"{s:.3f}" for s in r["spacing_per_lengthscale"])
        console.print(
            f"node spacing / smallest lengthscale per axis [v_ref, omega_ref, v, omega]: {spacing_txt}; "
            f"{r['grid_n_nodes']} nodes: per-terrain float32 table {r['table_mb']:.1f} MB, collapsed (nodes, 4) "
            f"table {r['collapsed_table_mb']:.1f} MB"
        )
        console.print(
            f"predictions/s (all {len(r['tasks'])} tasks, mean + variance; shared machine, timings noisy): "
            f"exact {r['exact_per_s']:.3g}, exact mean-only {r['exact_mean_only_per_s']:.3g}, "
            f"grid multilinear {r['grid_per_s']:.3g}, simplex {r['simplex_per_s']:.3g}; grid table "
            f"{'loaded' if r['grid_stored'] else 'built'} in {r['grid_setup_s']:.2f} s "
            f"({r['grid_setup_cpu_s']:.2f} s CPU)"
        )
