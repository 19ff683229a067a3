"""`gpmppi bench ...`: benchmarks that print numbers (speed goals live here, not in tests)."""

from __future__ import annotations

import typer

from tools import (
    bench_foxglove,
    bench_gp,
    bench_planner,
    bench_soak,
    bench_startup,
    bench_view,
    bench_viewer_stall,
    bench_zenoh,
)


def register(app: typer.Typer) -> None:
    bench_app = typer.Typer(help="Benchmarks: print timings and accuracy numbers.", no_args_is_help=True)
    for module in (bench_gp, bench_planner, bench_zenoh, bench_startup, bench_soak, bench_view, bench_viewer_stall,
                   bench_foxglove):
        module.register(bench_app)
    app.add_typer(bench_app, name="bench")
