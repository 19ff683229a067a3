"""`gpmppi bench soak --duration S`: the whole stack (router, sim, ingress, terrain, planner, egress and the
recorder; optionally the viewer) for S seconds, watched from outside:

- memory: every child process's resident set (VmRSS from /proc/<pid>/status) once a second; after a warm-up,
  its first, middle and last sample, min and max, growth (last vs first) and spread ((max - min) / min);
- recorder: every message an outside session saw while the stack was up, against what the MCAP file holds
  (matched by key and payload bytes, so a message recorded twice cannot hide one that was lost), and the totals
  per key the launcher's monitor counted next to the file's;
- planner: command rate, state stamp -> command p50 / p99 and plan compute p99 per time window;
- each service's rejected input (its last heartbeat), and every restart with its exit codes.

The S seconds count from the planner's first command (`up_s` after the services' start): a stack is up when it
commands, and how long a start takes is `gpmppi bench startup`'s measure, not the soak's.

Timings and rates are those of this machine at the time: on a shared machine they move with its load (the load
average is printed with them).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import typer
import zenoh
from mcap.reader import make_reader

from services.launch.launcher import run_launch
from services.launch.monitor import Monitor, Summary
from services.launch.supervisor import Launcher
from services.recording.mcap_io import REJECTED_SUFFIX, recording_files
from tools.cli_checks import OUT_FILE

UP_TIMEOUT_S = 120.0  # the longest wait for the planner's first command before the soak's clock starts anyway


def rss_kib(pid: int) -> int | None:
    """Resident set size of a process [KiB] (VmRSS in /proc/<pid>/status), or None when it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError, ValueError, IndexError):
        return None
    return None


def cpu_s(pid: int) -> float | None:
    """CPU time a process has used so far, user + system [s] (/proc/<pid>/stat), or None when it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (FileNotFoundError, ProcessLookupError, ValueError, IndexError):
        return None


@dataclass
class Tick:
    """One sample of the running stack, taken once a second."""

    t_s: float  # since the soak began (all services up and the planner commanding)
    rss_kib: dict[str, int]  # service -> resident set [KiB] (absent when its process was down)
    pids: dict[str, int]
    cmd_count: int  # commands the monitor has seen on `cmd` so far
    latencies: int  # length of the monitor's state stamp -> command list so far
    plans: int  # length of the monitor's plan compute time list so far
    cpu_s: dict[str, float] = field(default_factory=dict)  # process -> its CPU time so far [s]; spares as `name*`


@dataclass
class SoakData:
    ticks: list[Tick] = field(default_factory=list)
    seen: Counter[tuple[str, bytes]] = field(default_factory=Counter)  # (key, payload digest) seen from outside
    seen_per_key: Counter[str] = field(default_factory=Counter)
    latencies_ms: list[float] = field(default_factory=list)
    plan_ms: list[float] = field(default_factory=list)
    heartbeats: dict[str, dict] = field(default_factory=dict)
    monitor_counts: dict[str, int] = field(default_factory=dict)  # the monitor's per-key totals, at the end
    restarts: dict[str, dict] = field(default_factory=dict)
    soak_s: float = 0.0
    up_s: float | None = None  # from every service's start to the planner's first command [s] (None: none came)


def _digest(payload: bytes) -> bytes:
    return hashlib.blake2b(payload, digest_size=16).digest()


def soak_hook(duration_s: float, data: SoakData, sample_s: float = 1.0) -> Callable[[Launcher, Monitor], None]:
    """The `then` hook of `run_launch`: sample memory and counters for `duration_s`, and note every message an
    outside subscriber (on the monitor's session) receives meanwhile."""

    def soak(launcher: Launcher, monitor: Monitor) -> None:
        lock = threading.Lock()
        recording = threading.Event()
        recording.set()

        def on_sample(sample: zenoh.Sample) -> None:
            if sample.kind != zenoh.SampleKind.PUT or not recording.is_set():
                return
            key = str(sample.key_expr)
            digest = _digest(sample.payload.to_bytes())
            with lock:
                data.seen[(key, digest)] += 1
                data.seen_per_key[key] += 1

        sub = monitor.session.declare_subscriber("gpmppi/**", on_sample)
        cmd_key = f"gpmppi/{monitor.robot}/cmd"
        # the soak's clock starts once the planner commands: its heartbeat (what the launch waits for) comes before
        # it has loaded its kernels and taken states, and on a loaded machine that start took over 4 s, which the
        # first window after the warm-up then counted as a planner sending nothing (the start: `gpmppi bench startup`)
        started = time.monotonic()
        up_by = started + UP_TIMEOUT_S
        while not launcher.stop_event.is_set() and time.monotonic() < up_by:
            with monitor.lock:
                if monitor.counts[cmd_key] > 0:
                    data.up_s = time.monotonic() - started
                    break
            time.sleep(0.02)
        t0 = time.monotonic()
        next_tick = t0
        try:
            while not launcher.stop_event.is_set():
                now = time.monotonic()
                rss, pids, cpu = {}, {}, {}
                for child in launcher.children:
                    # each service's process, and its warm spare's (`name*`), if it has one
                    procs = [(child.name, child.process)]
                    if child.spare is not None:
                        procs.append((f"{child.name}*", child.spare.process))
                    for name, process in procs:
                        if process is not None and process.poll() is None:
                            kib, used = rss_kib(process.pid), cpu_s(process.pid)
                            if kib is not None and used is not None:
                                rss[name], pids[name], cpu[name] = kib, process.pid, used
                with monitor.lock:
                    tick = Tick(
                        round(now - t0, 3), rss, pids, monitor.counts[cmd_key], len(monitor.latencies_ms),
                        len(monitor.plan_total_ms), cpu,
                    )
                data.ticks.append(tick)
                if now - t0 >= duration_s:
                    break
                next_tick += sample_s
                launcher.stop_event.wait(max(0.0, next_tick - time.monotonic()))
        finally:
            # stop counting before the stack stops: every message counted here was sent while the recorder ran
            recording.clear()
            sub.undeclare()
            data.soak_s = time.monotonic() - t0
            # the monitor's own callback decodes each message, so on a loaded machine it may still be handling the
            # last few commands the counter above has seen: its totals are read once it has caught up (or after 2 s)
            caught_up_by = time.monotonic() + 2.0
            while time.monotonic() < caught_up_by:
                with monitor.lock, lock:
                    if monitor.counts[cmd_key] >= data.seen_per_key[cmd_key]:
                        break
                time.sleep(0.01)
            with monitor.lock:
                data.latencies_ms = list(monitor.latencies_ms)
                data.plan_ms = list(monitor.plan_total_ms)
                data.monitor_counts = dict(monitor.counts)
                fields = {"received", "rejected", "published", "last_error", "status", "counts"}
                data.heartbeats = {k: hb.model_dump(include=fields) for k, hb in monitor.heartbeats.items()}
            data.restarts = {
                c.name: {"restarts": c.restarts, "exit_codes": list(c.exit_codes), "failed": c.failed}
                for c in launcher.children
                if c.restarts or c.exit_codes or c.failed
            }

    return soak


def recorded(path: str | Path) -> tuple[Counter[tuple[str, bytes]], Counter[str]]:
    """(key, payload digest) and per-key counts of every message in an MCAP recording, rotated parts included
    (raw: valid or not)."""
    by_payload: Counter[tuple[str, bytes]] = Counter()
    per_key: Counter[str] = Counter()
    for part in recording_files(path) or [Path(path)]:
        with open(part, "rb") as f:
            for _, channel, message in make_reader(f).iter_messages():
                # a payload that broke its key's schema is kept on `<key>/_rejected`: recorded, not lost
                by_payload[(channel.topic.removesuffix(REJECTED_SUFFIX), _digest(message.data))] += 1
                per_key[channel.topic] += 1
    return by_payload, per_key


def memory_report(ticks: list[Tick], warmup_s: float) -> dict[str, dict]:
    """Per service, over the samples after the warm-up (of its current process, if it was restarted): start,
    middle, end, min, max [MiB], growth (end vs start) and spread ((max - min) / min) [%]."""
    out: dict[str, dict] = {}
    names = dict.fromkeys(name for t in ticks for name in t.rss_kib)
    for name in names:
        series = [(t.t_s, t.rss_kib[name], t.pids[name]) for t in ticks if name in t.rss_kib]
        last_pid = series[-1][2]
        after = [(ts, kib) for ts, kib, pid in series if ts >= warmup_s and pid == last_pid]
        if not after:
            continue
        mib = np.array([kib for _, kib in after], dtype=np.float64) / 1024.0
        start, end = float(mib[0]), float(mib[-1])
        # CPU over the same samples: % of one core
        used = [(t.t_s, t.cpu_s[name]) for t in ticks
                if name in t.cpu_s and t.t_s >= warmup_s and t.pids.get(name) == last_pid]
        cpu_pct = (round(100.0 * (used[-1][1] - used[0][1]) / (used[-1][0] - used[0][0]), 2)
                   if len(used) > 1 and used[-1][0] > used[0][0] else None)
        out[name] = {
            "samples": len(after),
            "pid": last_pid,
            "cpu_pct": cpu_pct,
            "start_mib": round(start, 1),
            "middle_mib": round(float(mib[len(mib) // 2]), 1),
            "end_mib": round(end, 1),
            "min_mib": round(float(mib.min()), 1),
            "max_mib": round(float(mib.max()), 1),
            "growth_pct": round(100.0 * (end - start) / start, 2),
            "spread_pct": round(100.0 * (float(mib.max()) - float(mib.min())) / float(mib.min()), 2),
            # every 10th sample [s, MiB]: the shape over time
            "series": [[round(ts, 1), round(kib / 1024.0, 1)] for ts, kib in after[::10]],
        }
    return out


def planner_windows(data: SoakData, warmup_s: float, window_s: float, sample_s: float = 1.0) -> list[dict]:
    """Command rate [Hz], state stamp -> command p50 / p99 [ms] and plan compute p99 [ms] per window of
    `window_s` from the end of the warm-up (each window's ends are the samples nearest its boundaries)."""

    def tick_at(t: float) -> Tick | None:
        return next((k for k in data.ticks if k.t_s >= t - sample_s / 2), None)

    windows = []
    k = 0
    while (a := tick_at(warmup_s + k * window_s)) is not None and (b := tick_at(warmup_s + (k + 1) * window_s)):
        k += 1
        if b.t_s - a.t_s < window_s / 2:  # the run ended inside this window
            break
        lat = np.array(data.latencies_ms[a.latencies : b.latencies])
        plan = np.array(data.plan_ms[a.plans : b.plans])
        windows.append({
            "t0_s": round(a.t_s, 1),
            "t1_s": round(b.t_s, 1),
            "commands": b.cmd_count - a.cmd_count,
            "rate_hz": round((b.cmd_count - a.cmd_count) / (b.t_s - a.t_s), 2),
            "latency_p50_ms": round(float(np.percentile(lat, 50)), 2) if lat.size else None,
            "latency_p99_ms": round(float(np.percentile(lat, 99)), 2) if lat.size else None,
            "plan_p99_ms": round(float(np.percentile(plan, 99)), 2) if plan.size else None,
        })
    return windows


def soak(
    duration_s: float,
    port: int | None = None,
    record: str | Path | None = None,
    warmup_s: float | None = None,
    window_s: float | None = None,
    launch: str | Path | None = None,
    viewer: bool = False,
    show_logs: bool = False,
) -> dict:
    """Run the soak and return its report (see the module docstring)."""
    warmup_s = min(60.0, 0.2 * duration_s) if warmup_s is None else warmup_s
    window_s = max(1.0, (duration_s - warmup_s) / 10) if window_s is None else window_s
    tmp = tempfile.TemporaryDirectory(prefix="gpmppi-soak-")
    record = str(record) if record is not None else str(Path(tmp.name) / "soak.mcap")
    rerun = ["save", str(Path(tmp.name) / "soak.rrd")] if viewer else None
    data = SoakData()
    load_before = os.getloadavg()[0]
    logs = None if show_logs else io.StringIO()
    try:
        code, summary = run_launch(launch, record=record, rerun=rerun, port=port, out=logs,
                                   then=soak_hook(duration_s, data))
        report = build_report(data, summary, record, warmup_s, window_s)
    finally:
        tmp.cleanup()
    report["exit_code"] = code
    report["load_avg_1min"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]
    return report


def build_report(data: SoakData, summary: Summary, record: str, warmup_s: float, window_s: float) -> dict:
    in_file, file_per_key = recorded(record)
    lost = {}
    for (key, digest), n in data.seen.items():
        missing = n - in_file.get((key, digest), 0)
        if missing > 0:
            lost[key] = lost.get(key, 0) + missing
    windows = planner_windows(data, warmup_s, window_s)
    rates = [w["rate_hz"] for w in windows]
    memory = memory_report(data.ticks, warmup_s)
    return {
        "duration_s": round(data.soak_s, 1),
        "up_s": None if data.up_s is None else round(data.up_s, 2),
        "warmup_s": warmup_s,
        "window_s": window_s,
        "memory": memory,
        "memory_max_spread_pct": max((m["spread_pct"] for m in memory.values()), default=None),
        # the warm spares (`name*`): what they cost while they wait, in % of one core and MiB resident
        "spares": {
            "n": sum(name.endswith("*") for name in memory),
            "cpu_pct": round(sum(m["cpu_pct"] or 0.0 for n, m in memory.items() if n.endswith("*")), 2),
            "rss_mib": round(sum(m["end_mib"] for n, m in memory.items() if n.endswith("*")), 1),
        },
        "services_cpu_pct": round(sum(m["cpu_pct"] or 0.0 for n, m in memory.items() if not n.endswith("*")), 2),
        "recorder": {
            "seen_while_up": sum(data.seen_per_key.values()),
            "lost": sum(lost.values()),
            "lost_per_key": lost,
            "in_file": sum(file_per_key.values()),
            # per key: seen from outside while every service was up; the launcher's monitor since the launch began
            # (it misses what came before its session opened); the file, from the recorder's start to its stop
            "per_key": {
                k: {"seen_while_up": data.seen_per_key.get(k, 0), "monitor": data.monitor_counts.get(k, 0),
                    "recorded": file_per_key.get(k, 0)}
                for k in sorted(set(data.seen_per_key) | set(file_per_key) | set(data.monitor_counts))
            },
        },
        "planner": {
            "windows": windows,
            "rate_hz_min": min(rates, default=None),
            "rate_hz_max": max(rates, default=None),
            "rate_hz_mean": round(float(np.mean(rates)), 2) if rates else None,
            "rate_cv_pct": round(100.0 * float(np.std(rates) / np.mean(rates)), 2) if rates and min(rates) else None,
            "latency_p99_ms_max": max((w["latency_p99_ms"] for w in windows if w["latency_p99_ms"] is not None),
                                      default=None),
        },
        "rejected": {k: hb["rejected"] for k, hb in sorted(data.heartbeats.items())},
        "heartbeats": data.heartbeats,
        "restarts": data.restarts,
        "failed": summary.failed,
        "lane_rmse_mm": None if summary.lane_rmse_mm is None else round(summary.lane_rmse_mm, 1),
        "distance_driven_m": round(summary.distance_driven_m, 1),
    }


def print_report(r: dict) -> None:
    up = "no command came" if r["up_s"] is None else f"from {r['up_s']} s after the services' start"
    typer.echo(f"soak {r['duration_s']} s ({up}: the planner's first command; warm-up {r['warmup_s']} s), load "
               f"average (1 min) before, after: {r['load_avg_1min']}, exit code {r['exit_code']}")
    typer.echo("memory after warm-up [MiB]: start / middle / end, max; growth, spread; CPU [% of one core]"
               " (name*: a warm spare)")
    for name, m in r["memory"].items():
        typer.echo(f"  {name:>9}: {m['start_mib']} / {m['middle_mib']} / {m['end_mib']}, max {m['max_mib']}; "
                   f"growth {m['growth_pct']:+.1f} %, spread {m['spread_pct']:.1f} % (n {m['samples']}); "
                   f"CPU {m['cpu_pct']} %")
    sp = r["spares"]
    typer.echo(f"warm spares: {sp['n']}, CPU {sp['cpu_pct']} % of one core, {sp['rss_mib']} MiB resident; "
               f"the services: CPU {r['services_cpu_pct']} %")
    rec = r["recorder"]
    typer.echo(f"recorder: {rec['seen_while_up']} messages seen while up, {rec['lost']} of them not in the file "
               f"{rec['lost_per_key'] or ''}; {rec['in_file']} in the file")
    for key, row in rec["per_key"].items():
        typer.echo(f"  {key}: seen {row['seen_while_up']}, monitor {row['monitor']}, recorded {row['recorded']}")
    p = r["planner"]
    typer.echo(f"planner: rate {p['rate_hz_min']}..{p['rate_hz_max']} Hz (mean {p['rate_hz_mean']}, "
               f"cv {p['rate_cv_pct']} %), worst window p99 {p['latency_p99_ms_max']} ms")
    for w in p["windows"]:
        typer.echo(f"  {w['t0_s']:>7}-{w['t1_s']:<7} s: {w['rate_hz']} Hz, state -> cmd p50 {w['latency_p50_ms']} "
                   f"p99 {w['latency_p99_ms']} ms, plan p99 {w['plan_p99_ms']} ms")
    typer.echo(f"rejected input (last heartbeat): {r['rejected']}")
    typer.echo(f"restarts: {r['restarts'] or 'none'}; failed: {r['failed'] or 'none'}")
    typer.echo(f"lane RMSE {r['lane_rmse_mm']} mm, driven {r['distance_driven_m']} m")


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("soak")
    def bench_soak(
        duration: float = typer.Option(
            600.0, min=5.0, max=7 * 86400.0, help="seconds of running once every service is up"
        ),
        port: int = typer.Option(7463, min=1, max=65535, help="router port on 127.0.0.1"),
        warmup: float | None = typer.Option(
            None, min=0.0, help="seconds excluded from memory and rate (default: 20 %, <= 60)"
        ),
        window: float | None = typer.Option(
            None, min=0.1, help="planner window [s] (default: a tenth after warm-up)"
        ),
        record: Path | None = typer.Option(
            None, metavar=OUT_FILE, help="keep the recording here (default: a temporary file)"
        ),
        viewer: bool = typer.Option(False, help="run the viewer too (saving an .rrd to a temporary file)"),
        launch_file: Path | None = typer.Option(None, help="launch YAML (default: the simulated Jackal)"),
        as_json: bool = typer.Option(False, "--json", help="print one JSON object instead of text"),
        show_logs: bool = typer.Option(False, help="print the services' logs too"),
    ) -> None:
        """Memory per service, recorder completeness, planner rate and latency over time, rejections and restarts
        of the whole stack run for --duration seconds."""
        report = soak(duration, port, record, warmup, window, launch_file, viewer, show_logs)
        if as_json:
            typer.echo(json.dumps(report))
        else:
            print_report(report)
        raise typer.Exit(report["exit_code"])
