"""`gpmppi bench startup`: how long a service takes to be useful again when it is (re)started on its own while
the rest of the stack runs (a crashed planner restarted by the launcher or systemd: the robot waits for it), and
how long its warm spare takes to take over when it is killed.

The whole stack starts as `gpmppi launch` runs it (the cold start of every process at once, reported as
`bench zenoh` does); once every service is up and the stack has settled, each service in turn is stopped as the
launcher stops it (SIGINT, then SIGTERM, then SIGKILL) and started again at once, `repeats` times. Time to first
output = from the new process's start (its Popen) to its first message on its output key (`PRIMARY_OUTPUT`) as
the launcher's outside Zenoh client receives it; a message numbered after the old process's last one (header
seq; a new process counts from 0) is a late delivery from the old process and does not count. Ready = from the
new process's start to its "ready" on the launcher's role socket (loaded, about to join).

Then (`kills`) each service in turn is killed with SIGKILL while the robot drives, once its warm spare is ready:
kill -> the new process's first output at the outside client, the dead process's last output -> that, and for the
planner the base's first zero after the dead planner's last command, driving again (a moving base command from the
planner) after it, and the lane RMSE over the 5 s after the takeover against the 5 s before the kill.
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
from services.launch.processes import Child
from services.launch.supervisor import Launcher
from tools.bench_takeover import Takeover, first_output, kill_rounds, no_kill_reference
from tools.cli_checks import OUT_FILE

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
    ready_s: float | None = None  # new process start -> its "ready" on the launcher's role socket


@dataclass
class StartupResult:
    restarts: list[Restart] = field(default_factory=list)
    takeovers: list[Takeover] = field(default_factory=list)
    summary: Summary | None = None
    exit_code: int = 0
    load_avg_1min: list[float] = field(default_factory=list)  # before and after the whole run
    # the lane RMSE ratio of consecutive 5 s windows where nothing was killed (`lane_windows`): the reference for
    # the takeovers' after / before ratios
    no_kill_ratio: dict[str, float | int | None] = field(default_factory=dict)

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
                "ready_p50_s": _pct([r.ready_s for r in self.restarts if r.service == name], 50),
            }
        return out

    def per_takeover(self) -> dict[str, dict[str, float | int | None]]:
        """service -> n, by spare, p50/p95/max of kill -> first output and of the output gap [s], the zero's and
        driving's times after the last command [s], and the RMSE before and after [mm] (medians)."""
        out: dict[str, dict[str, float | int | None]] = {}
        for name in dict.fromkeys(t.service for t in self.takeovers):
            rows = [t for t in self.takeovers if t.service == name]
            kill = [t.kill_to_output_s for t in rows]
            gap = [t.gap_s for t in rows]
            zero = [t.zero_after_last_cmd_s for t in rows]
            out[name] = {
                "n": len(rows),
                "by_spare": sum(t.by_spare for t in rows),
                "timeouts": sum(t.kill_to_output_s is None for t in rows),
                "spare_ready_p50_s": _pct([t.spare_ready_s for t in rows], 50),
                "kill_to_output_p50_s": _pct(kill, 50),
                "kill_to_output_p95_s": _pct(kill, 95),
                "kill_to_output_max_s": _pct(kill, 100),
                "gap_p50_s": _pct(gap, 50),
                "gap_p95_s": _pct(gap, 95),
                "gap_max_s": _pct(gap, 100),
                "zeros": sum(z is not None for z in zero),
                "zero_after_last_cmd_max_s": _pct(zero, 100),
                "driving_after_last_cmd_p95_s": _pct([t.driving_after_last_cmd_s for t in rows], 95),
                "rmse_before_p50_mm": _pct([t.rmse_before_mm for t in rows], 50),
                "rmse_after_p50_mm": _pct([t.rmse_after_mm for t in rows], 50),
                "rmse_after_over_before_max": _pct(
                    [t.rmse_after_mm / t.rmse_before_mm if t.rmse_after_mm and t.rmse_before_mm else None
                     for t in rows], 100),
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
            "takeover": self.per_takeover(),
            "takeovers": [asdict(t) for t in self.takeovers],
            "no_kill_rmse_ratio": self.no_kill_ratio,
        }


def _pct(values: list[float | None], q: float) -> float | None:
    vals = [v for v in values if v is not None]
    return round(float(np.percentile(vals, q)), 3) if vals else None


def restart_rounds(
    services: list[str], repeats: int, settle_s: float, timeout_s: float, records: list[Restart]
) -> Callable[[Launcher, Monitor], None]:
    """The `then` hook of `run_launch`: settle, then restart each service `repeats` times, one at a time."""

    def restart_each_service(launcher: Launcher, monitor: Monitor) -> None:
        # the settling time counts from when each service publishes steadily, not from the launch: under load a cold
        # start takes seconds, and a sim at a load of 8 published its first output, then its second only after the
        # settling time (the restart then found one old output to compare with)
        for name in services:
            child = next(c for c in launcher.children if c.name == name)
            key = f"gpmppi/{monitor.robot}/{PRIMARY_OUTPUT[child.kind]}"
            steady_output(launcher, monitor, key, child.started_at, timeout_s)
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
                first = first_output(launcher, monitor, key, started, old_last, timeout_s)
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
                        ready_s=_ready_s(child),
                    )
                )
                shown = "timed out" if first is None else f"{first[0] - started:.2f} s"
                launcher.say("bench", f"restarted {name} (pid {child.process.pid}): first output after {shown}")
                # let the stack recover (downstream services resume) before the next restart; the settling time
                # counts from when the new process publishes steadily, as at the start (a sim at a load of 5 published
                # its second output only after the settling time: the next restart found one old output)
                steady_output(launcher, monitor, key, started, timeout_s)
                if launcher.stop_event.wait(settle_s):
                    return

    return restart_each_service


def steady_output(launcher: Launcher, monitor: Monitor, key: str, started: float, timeout_s: float,
                  outputs: int = 3) -> bool:
    """Wait until the process started at `started` has published `outputs` times on `key` (False after
    `timeout_s` or once the launch stops)."""
    deadline = started + timeout_s
    while time.monotonic() < deadline and not launcher.stop_event.is_set():
        with monitor.lock:
            if sum(t >= started for t, _ in monitor.output_arrivals[key]) >= outputs:
                return True
        time.sleep(0.01)
    return False


def _ready_s(child: Child, timeout_s: float = 60.0) -> float | None:
    """The current process's start -> its ready on the role socket [s], waiting for it up to `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        proc = child.proc
        if proc is not None and proc.ready_at is not None:
            return round(proc.ready_at - proc.started_at, 3)
        time.sleep(0.02)
    return None


def measure_startup(
    launch_path: str | Path | None = None,
    services: list[str] | None = None,
    repeats: int = 3,
    settle_s: float = 3.0,
    timeout_s: float = 60.0,
    port: int | None = None,
    show_logs: bool = False,
    kills: int = 0,
    kill_services: list[str] | None = None,
    record: str | Path | None = None,
    kill_jitter_s: float = 0.0,
    seed: int = 0,
) -> StartupResult:
    """Cold-start the stack, then restart each service in turn `repeats` times, then kill each of `kill_services`
    `kills` times (its spare takes over); see the module docstring. `record`: an MCAP file the stack records to (the
    recorder runs beside it, as `gpmppi launch --record`), kept to look into a takeover afterwards."""
    services = services or RESTARTABLE
    kill_services = kill_services or []
    unknown = [s for s in services + kill_services if s not in PRIMARY_OUTPUT]
    if unknown:
        raise ValueError(f"cannot measure the restart of {unknown}: services with an output key are {RESTARTABLE}")
    result = StartupResult()
    before = os.getloadavg()[0]
    restarts = restart_rounds(services, repeats, settle_s, timeout_s, result.restarts)
    takeovers = kill_rounds(kill_services, kills, settle_s, timeout_s, result.takeovers, kill_jitter_s, seed)

    def hook(launcher: Launcher, monitor: Monitor) -> None:
        restarts(launcher, monitor)
        if not launcher.stop_event.is_set():
            begin_ns = time.time_ns()
            takeovers(launcher, monitor)
            result.no_kill_ratio = no_kill_reference(monitor, result.takeovers, begin_ns)

    hook.__name__ = "restarts_then_kills"
    logs = None if show_logs else io.StringIO()
    result.exit_code, result.summary = run_launch(launch_path, record=None if record is None else str(record),
                                                   port=port, out=logs, then=hook)
    result.load_avg_1min = [round(before, 2), round(os.getloadavg()[0], 2)]
    return result


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("startup")
    def bench_startup(
        services: str = typer.Option(",".join(RESTARTABLE), help="comma-separated services to restart, in order"),
        repeats: int = typer.Option(3, min=0, max=1000, help="restarts of each service"),
        kills: int = typer.Option(
            1, min=0, max=1000, help="then SIGKILLs of each --kill-services service while the robot drives, each "
            "once its warm spare is ready (the takeover)"
        ),
        kill_services: str = typer.Option(
            "planner,terrain,ingress,egress", help="comma-separated services to kill, in order"
        ),
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
        kill_jitter: float = typer.Option(
            10.0, min=0.0, max=600.0, help="wait a further random 0 to this many seconds before each kill, so that "
            "kills fall at different plan counts (a planner's noise is seeded by its count) [s]"
        ),
        seed: int = typer.Option(0, min=0, help="seed of the kills' random waits"),
        record: Path | None = typer.Option(
            None, metavar=OUT_FILE, help="record the run to this MCAP file (the recorder runs beside the stack; the "
            "takeovers' kill_ns and first_output_ns in --json find the kills in it)"
        ),
    ) -> None:
        """Time to first output of each service restarted on its own while the stack runs, and of the cold start
        of the whole stack (timings are noisy on a shared machine: see the load average)."""
        names = [s.strip() for s in services.split(",") if s.strip()]
        killed = [s.strip() for s in kill_services.split(",") if s.strip()]
        try:
            result = measure_startup(launch_file, names, repeats, settle, timeout, port, show_logs, kills, killed,
                                     record, kill_jitter, seed)
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
                    f"  {name:>8}: p50 {row['p50_s']}  max {row['max_s']}  (n {row['n']}, timeouts {row['timeouts']}); "
                    f"process start -> ready p50 {row['ready_p50_s']}"
                )
            if data["takeover"]:
                typer.echo("SIGKILL while driving [s]:")
            for name, row in data["takeover"].items():
                typer.echo(
                    f"  {name:>8}: n {row['n']} (by a warm spare {row['by_spare']}, timeouts {row['timeouts']}); "
                    f"spare start -> ready p50 {row['spare_ready_p50_s']}; kill -> first output p50 "
                    f"{row['kill_to_output_p50_s']} p95 {row['kill_to_output_p95_s']} "
                    f"max {row['kill_to_output_max_s']}; "
                    f"last output -> first output p50 {row['gap_p50_s']} p95 {row['gap_p95_s']} max {row['gap_max_s']}"
                )
                typer.echo(
                    f"  {'':>8}  last command -> base zero: {row['zeros']} zeros, "
                    f"max {row['zero_after_last_cmd_max_s']};"
                    f" -> driving again p95 {row['driving_after_last_cmd_p95_s']}; lane RMSE 5 s before "
                    f"{row['rmse_before_p50_mm']} mm, 5 s after {row['rmse_after_p50_mm']} mm (p50; worst ratio "
                    f"{row['rmse_after_over_before_max']})"
                )
            if ref := data["no_kill_rmse_ratio"]:
                typer.echo(
                    f"  reference, the same ratio of consecutive 5 s windows with no kill: n {ref['n']}, p50 "
                    f"{ref['p50']} p95 {ref['p95']} max {ref['max']}, above {ref['limit']} in {ref['share_over_limit']}"
                )
            typer.echo(f"cold start of the whole stack, start -> first output [s]: {data['cold_first_output_s']}")
            typer.echo(f"cold start, process start -> first heartbeat [s]: {data['cold_first_heartbeat_s']}")
            typer.echo(f"crash restarts: {data['crash_restarts'] or 'none'}; failed: {data['failed'] or 'none'}")
        timed_out = any(r.first_output_s is None for r in result.restarts) or any(
            t.kill_to_output_s is None for t in result.takeovers)
        raise typer.Exit(result.exit_code or int(timed_out))
