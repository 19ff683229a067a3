"""CLI of the services area: `gpmppi service`, `gpmppi launch`, `gpmppi demo`, `gpmppi schemas export`."""

from __future__ import annotations

import json
from pathlib import Path

import typer

PASS_THROUGH = {"allow_extra_args": True, "ignore_unknown_options": True, "help_option_names": []}


def register(app: typer.Typer) -> None:
    """Add this module's commands to `app`."""

    @app.command("service")
    def service(
        name: str = typer.Argument(..., help="router, sim, ingress, terrain, planner, egress, recorder or viewer"),
        config: Path | None = typer.Option(None, "--config", help="YAML settings file"),
    ) -> None:
        """Run one service (what the launcher and systemd units call)."""
        from services.run import SERVICES, run_service

        if name not in SERVICES:
            raise typer.BadParameter(f"unknown service {name!r}; known: {', '.join(SERVICES)}")
        raise typer.Exit(run_service(name, config))

    @app.command("launch", context_settings=PASS_THROUGH)
    def launch(ctx: typer.Context) -> None:
        """Run a launch file: [LAUNCH.yaml] [--duration S] [--record FILE.mcap]
        [--rerun spawn|save FILE|connect URL|serve|off] [--port N] [--secrets DIR]. No file: the simulated Jackal on the
        circle lane. --secrets DIR (from `gpmppi secure init DIR`) runs it with authentication and access control."""
        from services.launch.launcher import main

        raise typer.Exit(main(list(ctx.args)))

    @app.command("demo")
    def demo(
        duration: float = typer.Option(20.0, help="seconds to run"),
        out_dir: Path = typer.Option(Path("runs"), help="where demo.mcap and demo.rrd go"),
        port: int | None = typer.Option(None, help="router port on 127.0.0.1 (default 7447)"),
    ) -> None:
        """The main job: the simulated Jackal on the circle lane for ~20 s, recorded to runs/demo.mcap and
        saved for rerun in runs/demo.rrd, then a summary."""
        from services.launch.launcher import main

        out_dir.mkdir(parents=True, exist_ok=True)
        argv = ["--duration", str(duration), "--record", str(out_dir / "demo.mcap")]
        argv += ["--rerun", "save", str(out_dir / "demo.rrd")]
        if port is not None:
            argv += ["--port", str(port)]
        code = main(argv)
        typer.echo(f"recording: {out_dir / 'demo.mcap'}  rerun: {out_dir / 'demo.rrd'} (open with `rerun FILE`)")
        raise typer.Exit(code)

    schemas_app = typer.Typer(help="Message schemas.", no_args_is_help=True)

    @schemas_app.command("export")
    def export(out_dir: Path = typer.Argument(..., help="folder to write <Model>.schema.json files to")) -> None:
        """Write the JSON Schema of every message and a keys.json (key template -> message)."""
        from schemas import KEYS
        from schemas.messages import MODELS

        out_dir.mkdir(parents=True, exist_ok=True)
        for name, model in MODELS.items():
            (out_dir / f"{name}.schema.json").write_text(json.dumps(model.model_json_schema(), indent=2) + "\n")
        keys = {template: model.__name__ for template, model in KEYS.values()}
        (out_dir / "keys.json").write_text(json.dumps(keys, indent=2) + "\n")
        typer.echo(f"wrote {len(MODELS)} schemas and keys.json to {out_dir}")

    app.add_typer(schemas_app, name="schemas")
