"""The `gpmppi` command: one typer app; each area registers its commands from its own module."""

from __future__ import annotations

import typer

from tools import bench, dataset, evaluate, gp_cmd, inspect_cmd, replay, secure_cmd, service_cmd, train, warm

app = typer.Typer(
    name="gpmppi",
    help="Chance-constrained GP-MPPI for skid-steer robots.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
for _module in (dataset, train, gp_cmd, bench, evaluate, service_cmd, secure_cmd, inspect_cmd, replay, warm):
    _module.register(app)

if __name__ == "__main__":
    app()
