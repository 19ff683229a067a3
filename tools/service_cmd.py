"""CLI of the services area: `gpmppi service`, `gpmppi launch`, `gpmppi demo`, `gpmppi schemas export`."""

from __future__ import annotations

import json
from enum import Enum
from pathlib import Path
from typing import Any

import typer

from tools.cli_checks import OUT_DIR, RECORDING, fail, write_text_atomic

SERVICE_NAMES = ("router", "sim", "ingress", "terrain", "planner", "egress", "nav", "recorder", "viewer", "foxglove",
                 "calibrate")
DurationOpt = typer.Option(
    None, "--duration", min=0.1, max=30 * 86400.0, help="stop after this many seconds once every service is up"
)
PortOpt = typer.Option(None, "--port", min=1, max=65535, help="router port on 127.0.0.1 (overrides the file)")
FOXGLOVE_HELP = (
    "serve the run to Foxglove on this WebSocket address, HOST:PORT or PORT (loopback unless HOST says otherwise; "
    "see docs/foxglove.md)"
)


def foxglove_address(text: str | None) -> tuple[str, int] | None:
    """`--foxglove HOST:PORT` or `PORT` (host 127.0.0.1) as (host, port); a bad address is one line, exit 2."""
    if text is None:
        return None
    host, _, port = text.rpartition(":")
    host = host.strip("[]") or "127.0.0.1"
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        fail(f"--foxglove {text!r}: expected HOST:PORT or PORT with a port in 1..65535, e.g. 127.0.0.1:8765")
    return host, int(port)


class RerunMode(str, Enum):
    """Where the viewer service sends the run (`--rerun`)."""

    spawn = "spawn"
    save = "save"
    connect = "connect"
    serve = "serve"
    off = "off"


def _launch(
    launch_file: Path | None, duration: float | None, record: Path | None, rerun: list[str] | None,
    port: int | None, secrets: Path | None = None, foxglove: tuple[str, int] | None = None,
) -> tuple[int, Any]:
    """Run a launch file through the launcher: (exit code, summary); a launch that cannot start is one line."""
    from services.launch.launcher import RouterUnreachable, run_launch

    try:
        return run_launch(launch_file, duration, None if record is None else str(record), rerun, port,
                          secrets=None if secrets is None else str(secrets), foxglove=foxglove)
    except (FileNotFoundError, ValueError, TimeoutError, RouterUnreachable) as exc:
        fail(str(exc))
        raise AssertionError from exc  # fail() raises


def _rerun_args(mode: RerunMode | None, target: str | None) -> list[str] | None:
    if mode is None:
        if target is not None:
            fail(f"--rerun-target {target!r}: only with --rerun save (a .rrd file) or --rerun connect (a URL)")
        return None
    if mode in (RerunMode.save, RerunMode.connect):
        if target is None:
            fail(f"--rerun {mode.value} needs --rerun-target ({'FILE.rrd' if mode is RerunMode.save else 'URL'})")
        return [mode.value, target]
    if target is not None:
        fail(f"--rerun-target: --rerun {mode.value} takes no target")
    return [mode.value]


def register(app: typer.Typer) -> None:
    """Add this module's commands to `app`."""

    @app.command("service")
    def service(
        name: str = typer.Argument(..., help=", ".join(SERVICE_NAMES)),
        config: Path | None = typer.Option(None, "--config", help="YAML settings file"),
    ) -> None:
        """Run one service (what the launcher and systemd units call)."""
        from services.run import SERVICES, run_service

        if name not in SERVICES:
            fail(f"unknown service {name!r}; known: {', '.join(SERVICES)}")
        raise typer.Exit(run_service(name, config))

    @app.command("launch")
    def launch(
        launch_file: Path | None = typer.Argument(
            None, metavar="LAUNCH_FILE", help="launch YAML (default: the simulated Jackal on the circle lane)"
        ),
        duration: float | None = DurationOpt,
        record: Path | None = typer.Option(
            None, "--record", metavar=RECORDING,
            help="record everything to this MCAP file; an existing file is never replaced (a free -N name is "
                 "used and said), a folder gets a run-TIME.mcap inside",
        ),
        rerun: RerunMode | None = typer.Option(None, "--rerun", help="send the run to rerun"),
        rerun_target: str | None = typer.Option(
            None, "--rerun-target", help="with --rerun save: the .rrd file; with --rerun connect: the viewer's URL"
        ),
        port: int | None = PortOpt,
        secrets: Path | None = typer.Option(
            None, "--secrets", metavar="DIR",
            help="run with authentication and access control, with the identities of `gpmppi secure init DIR`",
        ),
        foxglove: str | None = typer.Option(None, "--foxglove", metavar="HOST:PORT", help=FOXGLOVE_HELP),
    ) -> None:
        """Run a launch file: every service as its own process, restarted on a crash, stopped on Ctrl-C; then a
        summary."""
        if launch_file is not None and launch_file.suffix == ".rrd":
            fail(f"LAUNCH_FILE {launch_file}: a rerun file, not a launch file; to save the view give "
                 f"--rerun save --rerun-target {launch_file}")
        address = foxglove_address(foxglove)
        code, _ = _launch(launch_file, duration, record, _rerun_args(rerun, rerun_target), port, secrets, address)
        raise typer.Exit(code)

    @app.command("demo")
    def demo(
        duration: float = typer.Option(20.0, "--duration", min=0.1, max=86400.0, help="seconds to run"),
        out_dir: Path = typer.Option(
            Path("runs"), "--output", "-o", metavar=OUT_DIR,
            help="where demo.mcap and demo.rrd go (an earlier demo's files are kept: a free -N name is used)",
        ),
        port: int | None = PortOpt,
    ) -> None:
        """The main job: the simulated Jackal on the circle lane for ~20 s, recorded to runs/demo.mcap and
        saved for rerun in runs/demo.rrd, then a summary."""
        out_dir.mkdir(parents=True, exist_ok=True)
        code, summary = _launch(None, duration, out_dir / "demo.mcap", ["save", str(out_dir / "demo.rrd")], port)
        typer.echo(f"recording: {summary.recording}  rerun: {summary.rerun_file} (open with `rerun FILE`)")
        raise typer.Exit(code)

    schemas_app = typer.Typer(help="Message schemas.", no_args_is_help=True)

    @schemas_app.command("export")
    def export(
        out_dir: Path = typer.Argument(..., metavar=OUT_DIR, help="folder to write <Model>.schema.json files to"),
        force: bool = typer.Option(False, "--force", help="replace schema files already in the folder"),
    ) -> None:
        """Write the JSON Schema of every message and a keys.json (key template -> message)."""
        from schemas import KEYS
        from schemas.messages import MODELS

        files = {f"{name}.schema.json": json.dumps(model.model_json_schema(), indent=2) + "\n"
                 for name, model in MODELS.items()}
        files["keys.json"] = json.dumps({t: m.__name__ for t, m in KEYS.values()}, indent=2) + "\n"
        existing = [n for n in files if (out_dir / n).exists()]
        if existing and not force:
            fail(f"{out_dir}: holds {', '.join(existing[:3])}{' ...' if len(existing) > 3 else ''} already; "
                 "add --force to replace them, or choose another folder")
        out_dir.mkdir(exist_ok=True)
        for name, text in files.items():
            write_text_atomic(out_dir / name, text)
        typer.echo(f"wrote {len(MODELS)} schemas and keys.json to {out_dir}")

    app.add_typer(schemas_app, name="schemas")
