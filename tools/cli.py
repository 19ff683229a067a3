"""The `gpmppi` command: one typer app; each area registers its commands from its own module.

Every command runs through `tools.cli_checks.CheckedGroup`: its values are checked before it starts, and an
expected error is one line and exit status 2 (docs/cli.md)."""

from __future__ import annotations

import typer

from tools import (
    bench,
    calibrate_cmd,
    dataset,
    evaluate,
    gp_cmd,
    inspect_cmd,
    replay,
    secure_cmd,
    service_cmd,
    train,
    warm,
)
from tools.cli_checks import CheckedGroup

app = typer.Typer(
    name="gpmppi",
    help="Chance-constrained GP-MPPI for skid-steer robots.",
    cls=CheckedGroup,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    context_settings={"help_option_names": ["-h", "--help"], "show_default": True},
)


@app.callback()
def main(
    debug: bool = typer.Option(
        False, "--debug", help="Print the traceback of an expected error too (also GPMPPI_DEBUG=1)."
    ),
) -> None:
    """Chance-constrained GP-MPPI for skid-steer robots."""


for _module in (
    dataset, train, gp_cmd, bench, evaluate, service_cmd, secure_cmd, inspect_cmd, replay, warm, calibrate_cmd
):
    _module.register(app)

if __name__ == "__main__":
    app()
