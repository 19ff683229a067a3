"""`gpmppi bench startup`: how long a service takes to be useful again when it is (re)started on its own while
the rest of the stack runs (a crashed planner restarted by the launcher or systemd: the robot waits for it).

The whole stack starts as `gpmppi launch` runs it (the cold start of every process at once, reported as
`bench zenoh` does); once every service is up and the stack has settled, each service in turn is stopped as the
launcher stops it (SIGINT, then SIGTERM, then SIGKILL) and started again at once, `repeats` times. Time to first
output = from the new process's start (its Popen) to its first message on its output key (`PRIMARY_OUTPUT`) as
the launcher's outside Zenoh client receives it; a message numbered after the old process's last one (header
seq; a new process counts from 0) is a late delivery from the old process and does not count.
"""

from __future__ import annotations

import io
import json
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import typer

from services.launch.launcher import run_launch
from services.launch.monitor import PRIMARY_OUTPUT, Monitor, Summary
from services.launch.supervisor import Launcher

RESTARTABLE = list(PRIMARY_OUTPUT)  # sim, ingress, terrain, planner, egress


@dataclass
class Restart:
    """One deliberate restart of one service."""

    service: str
    old_pid: int
    pid: int
    stop_s: float  # SIGINT -> the old process exited
    first_output_s: float | None  # new process start -> its first output at the outside client; None: timed out
    first_seq: int | None  # header seq of that output (the new process counts from 0)
    old_last_seq: int | None  # seq of the old process's last output seen before the restart
    load_avg_1min: float  # the machine's load when the restart began


@dataclass
class StartupResult:
    restarts: list[Restart] = field(default_factory=list)
    summary: Summary | None = None
    exit_code: int = 0
    load_avg_1min: list[float] = field(default_factory=list)  # before and after the whole run

    def per_service(self) -> dict[str, dict[str, float | int | None]]:
        """service -> n, timeouts, p50 and max of the restart time to first output [s]."""
        out: dict[str, dict[str, float | int | None]] = {}
        for name in dict.fromkeys(r.service for r in self.restarts):
            times = [r.first_output_s for r in self.restarts if r.service == name and r.first_output_s is not None]
            n = sum(r.service == name for r in self.restarts)
            out[name] = {
                "n": n,
                "timeouts": n - len(times),
                "p50_s": round(float(np.percentile(times, 50)), 3) if times else None,
                "max_s": round(max(times), 3) if times else None,
            }
        return out

    def to_json(self) -> dict:
        s = self.summary or Summary()
        return {
            "load_avg_1min": self.load_avg_1min,
            "restart_load_avg_1min": [r.load_avg_1min for r in self.restarts],
            "restart_first_output_s": self.per_service(),
            "cold_first_output_s": {k: round(v, 2) for k, v in s.first_output_s.items()},
            "cold_first_heartbeat_s": {k: round(v, 2) for k, v in s.first_heartbeat_s.items()},
            "crash_restarts": s.restarts,
            "failed": s.failed,
            "restarts": [asdict(r) for r in self.restarts],
        }


def restart_rounds(
    services: list[str], repeats: int, settle_s: float, timeout_s: float, records: list[Restart]
) -> Callable[[Launcher, Monitor], None]:
    """The `then` hook of `run_launch`: settle, then restart each service `repeats` times, one at a time."""

    def restart_each_service(launcher: Launcher, monitor: Monitor) -> None:
        if launcher.stop_event.wait(settle_s):
            return
        for _ in range(repeats):
            for name in services:
                child = next(c for c in launcher.children if c.name == name)
                key = f"gpmppi/{monitor.robot}/{PRIMARY_OUTPUT[child.kind]}"
                load = round(os.getloadavg()[0], 2)
                old_pid = child.process.pid if child.process is not None else -1
                t_stop = time.monotonic()
                launcher.restart(name)
                assert child.process is not None
                started = child.started_at
                with monitor.lock:
                    before = [seq for t, seq in monitor.output_arrivals[key] if t < started]
                old_last = before[-1] if before else None
                first = _first_output(launcher, monitor, key, started, old_last, timeout_s)
                records.append(
                    Restart(
                        service=name,
                        old_pid=old_pid,
                        pid=child.process.pid,
                        stop_s=round(started - t_stop, 3),
                        first_output_s=None if first is None else round(first[0] - started, 3),
                        first_seq=None if first is None else first[1],
                        old_last_seq=old_last,
                        load_avg_1min=load,
                    )
                )
                shown = "timed out" if first is None else f"{first[0] - started:.2f} s"
                launcher.say("bench", f"restarted {name} (pid {child.process.pid}): first output after {shown}")
                # let the stack recover (downstream services resume) before the next restart
                if launcher.stop_event.wait(settle_s):
                    return

    return restart_each_service


def _first_output(
    launcher: Launcher, monitor: Monitor, key: str, started: float, old_last: int | None, timeout_s: float
) -> tuple[float, int] | None:
    """(arrival time, seq) of the new process's first output on `key`, or None after `timeout_s`."""
    deadline = started + timeout_s
    while time.monotonic() < deadline and not launcher.stop_event.is_set():
        with monitor.lock:
            arrivals = [(t, seq) for t, seq in monitor.output_arrivals[key] if t >= started]
        for t, seq in arrivals:
            if old_last is None or seq <= old_last:
                return t, seq
        time.sleep(0.005)  # the arrival time is taken on receipt: this poll does not add to it
    return None


def measure_startup(
    launch_path: str | Path | None = None,
    services: list[str] | None = None,
    repeats: int = 3,
    settle_s: float = 3.0,
    timeout_s: float = 60.0,
    port: int | None = None,
    show_logs: bool = False,
) -> StartupResult:
    """Cold-start the stack, then restart each service in turn `repeats` times; see the module docstring."""
    services = services or RESTARTABLE
    unknown = [s for s in services if s not in PRIMARY_OUTPUT]
    if unknown:
        raise ValueError(f"cannot measure the restart of {unknown}: services with an output key are {RESTARTABLE}")
    result = StartupResult()
    before = os.getloadavg()[0]
    hook = restart_rounds(services, repeats, settle_s, timeout_s, result.restarts)
    logs = None if show_logs else io.StringIO()
    result.exit_code, result.summary = run_launch(launch_path, port=port, out=logs, then=hook)
    result.load_avg_1min = [round(before, 2), round(os.getloadavg()[0], 2)]
    return result


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("startup")
    def bench_startup(
        services: str = typer.Option(",".join(RESTARTABLE), help="comma-separated services to restart, in order"),
        repeats: int = typer.Option(3, min=1, max=1000, help="restarts of each service"),
        settle: float = typer.Option(
            3.0, min=0.0, max=3600.0, help="seconds to wait after start-up and after each restart"
        ),
        timeout: float = typer.Option(
            60.0, min=1.0, max=3600.0, help="give up on a restarted service's first output after"
        ),
        launch_file: Path | None = typer.Option(None, help="launch YAML (default: the simulated Jackal)"),
        port: int = typer.Option(7462, min=1, max=65535, help="router port on 127.0.0.1"),
        as_json: bool = typer.Option(False, "--json", help="print one JSON object instead of text"),
        show_logs: bool = typer.Option(False, help="print the services' logs too"),
    ) -> None:
        """Time to first output of each service restarted on its own while the stack runs, and of the cold start
        of the whole stack (timings are noisy on a shared machine: see the load average)."""
        names = [s.strip() for s in services.split(",") if s.strip()]
        try:
            result = measure_startup(launch_file, names, repeats, settle, timeout, port, show_logs)
        except (ValueError, FileNotFoundError) as exc:
            typer.echo(f"gpmppi bench startup: {exc}", err=True)
            raise typer.Exit(2) from exc
        data = result.to_json()
        if as_json:
            typer.echo(json.dumps(data))
        else:
            typer.echo(f"load average (1 min) before, after: {data['load_avg_1min']}")
            typer.echo(f"at each restart: {data['restart_load_avg_1min']}")
            typer.echo("restart on its own, process start -> first output [s]:")
            for name, row in data["restart_first_output_s"].items():
                typer.echo(
                    f"  {name:>8}: p50 {row['p50_s']}  max {row['max_s']}  (n {row['n']}, timeouts {row['timeouts']})"
                )
            typer.echo(f"cold start of the whole stack, start -> first output [s]: {data['cold_first_output_s']}")
            typer.echo(f"cold start, process start -> first heartbeat [s]: {data['cold_first_heartbeat_s']}")
            typer.echo(f"crash restarts: {data['crash_restarts'] or 'none'}; failed: {data['failed'] or 'none'}")
        timed_out = any(r.first_output_s is None for r in result.restarts)
        raise typer.Exit(result.exit_code or int(timed_out))
