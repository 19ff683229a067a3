"""`gpmppi bench zenoh`: the whole stack over Zenoh on loopback (router + sim + ingress + terrain + planner +
egress, each its own process): planner rate, state-stamp -> command-publish latency p50/p99 (as the planner
measures it), state-stamp -> command received by an outside session, planner compute p99, each service's time
to its first heartbeat and first output, and the machine's load average around the run."""

from __future__ import annotations

import io
import json
import os
from pathlib import Path

import typer


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("zenoh")
    def bench_zenoh(
        launch: Path | None = typer.Option(
            None, "--launch-file", help="launch YAML (default: the simulated Jackal)"
        ),
        duration: float = typer.Option(20.0, min=1.0, max=86400.0, help="seconds of closed-loop running"),
        port: int = typer.Option(7461, min=1, max=65535, help="router port on 127.0.0.1"),
        as_json: bool = typer.Option(False, "--json", help="print one JSON object instead of text"),
        show_logs: bool = typer.Option(False, help="print the services' logs too"),
    ) -> None:
        """Planner rate and stamp -> command latency over Zenoh (timings are noisy on a shared machine)."""
        from services.launch.launcher import run_launch

        logs = io.StringIO()
        load_before = os.getloadavg()[0]
        code, s = run_launch(launch, duration=duration, port=port, out=None if show_logs else logs)
        result = {
            # the machine's 1-minute load average before and after (the stack itself adds about 1): timings on
            # a loaded machine are not those of an idle one
            "load_avg_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
            "duration_s": round(s.duration_s, 1),
            "planner_rate_hz": s.planner_rate_hz,
            "cmd_latency_p50_ms": s.latency_p50_ms,
            "cmd_latency_p99_ms": s.latency_p99_ms,
            "plan_compute_p99_ms": s.plan_p99_ms,
            # as an outside session (the launcher's) receives the command: adds the hop to it and its wake-up
            "cmd_received_p50_ms": s.delivery_p50_ms,
            "cmd_received_p99_ms": s.delivery_p99_ms,
            "cmd_messages": s.messages.get("gpmppi/jackal/cmd", 0),
            "first_heartbeat_s": {k: round(v, 2) for k, v in s.first_heartbeat_s.items()},
            "first_output_s": {k: round(v, 2) for k, v in s.first_output_s.items()},
            "lane_rmse_mm": s.lane_rmse_mm,
            "restarts": s.restarts,
            "failed": s.failed,
        }
        if as_json:
            typer.echo(json.dumps(result))
        else:
            for k, v in result.items():
                typer.echo(f"{k:>22}: {v}")
        raise typer.Exit(code)
