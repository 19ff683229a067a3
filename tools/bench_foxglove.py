"""`gpmppi bench foxglove`: the simulated stack's state -> command latency with the Foxglove server off, on with a
client connected, and with that client stopped (SIGSTOP), in interleaved rounds, so the spread between runs of the
same mode is read from the same run as the difference between modes.

One launch of the default stack, without `--foxglove`. Each round has three windows of `--window` seconds:

- `off`: no Foxglove server;
- `connected`: the Foxglove service started beside the stack (its own process, at the launcher's `nice 10`, as
  `gpmppi launch --foxglove` starts it) with a WebSocket client (its own process) reading as fast as it can;
- `client_stopped`: that client stopped with SIGSTOP.

The server is started before and stopped after each round's two server windows (the order of `connected` and
`client_stopped` alternates between rounds), with a few seconds' settling outside the windows. The client subscribes
to what the shipped layout shows (`--subscribe layout`, as Foxglove with that layout open does) or to every channel
(`--subscribe all`). The latency is the launcher monitor's: state stamp -> command received by the launcher's
session, and the planner's own state -> command published. The service's and the client's CPU time (per second of
window) are read from /proc.
"""

from __future__ import annotations

import io
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import typer
import yaml

LAYOUT = Path(__file__).resolve().parents[1] / "deploy" / "foxglove" / "gpmppi-layout.json"
MODES = ("off", "connected", "client_stopped")

# the client: connects with Foxglove's WebSocket protocol, subscribes to the channels named in argv[2] (a JSON list;
# null: every channel advertised), reads forever, at the CPU priority (nice) argv[3]
CLIENT = r"""
import json, os, sys
from websockets.sync.client import connect
os.nice(int(sys.argv[3]))
topics = json.loads(sys.argv[2])
with connect(sys.argv[1], subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"], open_timeout=30) as ws:
    print("connected", flush=True)
    while True:
        frame = ws.recv()
        if isinstance(frame, str):
            msg = json.loads(frame)
            if msg.get("op") == "advertise":
                subs = [{"id": c["id"], "channelId": c["id"]} for c in msg["channels"]
                        if topics is None or c["topic"] in topics]
                if subs:
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
"""


def layout_topics(layout: dict) -> set[str]:
    """The topics a Foxglove layout names: the 3D panel's topic settings, message paths' quoted topics, and the
    log panel's topic."""
    topics: set[str] = set()

    def walk(node: object, key: str = "") -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                if key == "topics" and isinstance(v, dict):
                    topics.add(k)
                walk(v, k)
        elif isinstance(node, list):
            for v in node:
                walk(v, key)
        elif isinstance(node, str) and key in ("value", "topicPath", "topicToRender"):
            # a message path names its topic in quotes ("gpmppi/jackal/state".v); a topic setting names it bare
            quoted = re.match(r'^"([^"]+)"', node)
            topics.add(quoted.group(1) if quoted else node.split(".")[0])

    walk(layout.get("configById", layout))
    return topics


def _percentiles(values: list[float]) -> dict:
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return {"n": 0}
    return {"n": int(a.size), "p50_ms": round(float(np.percentile(a, 50)), 2),
            "p99_ms": round(float(np.percentile(a, 99)), 2), "max_ms": round(float(a.max()), 2)}  # fmt: skip


def _cpu_s(pid: int) -> float:
    """User + system CPU time [s] of a running process (0 once it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Server:
    """The Foxglove service and one client, each its own process, for one round's server windows."""

    def __init__(
        self, port: int, ws_port: int, topics: list[str] | None, client_nice: int, config_dir: str, logs: io.StringIO
    ) -> None:
        config = Path(config_dir) / "foxglove.yaml"
        zenoh_cfg = {"mode": "client", "connect": [f"tcp/127.0.0.1:{port}"]}
        settings = {"service": "foxglove", "robot": "jackal", "zenoh": zenoh_cfg, "port": ws_port, "nice": 10}
        config.write_text(yaml.safe_dump(settings))
        self.logs = logs
        self.log_path = Path(config_dir) / "foxglove.log"
        with open(self.log_path, "w") as log:  # a file, not a pipe: a pipe nobody reads would stop the service
            self.service = subprocess.Popen(
                [sys.executable, "-m", "services.run", "foxglove", "--config", str(config)], stdout=log, stderr=log
            )
        deadline = time.monotonic() + 120
        while "foxglove: serving" not in self.log_path.read_text():  # once the server listens
            if self.service.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError("the Foxglove service did not start serving; --show-logs says why")
            time.sleep(0.1)
        self.client = subprocess.Popen(
            [sys.executable, "-c", CLIENT, f"ws://127.0.0.1:{ws_port}", json.dumps(topics), str(client_nice)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        assert self.client.stdout is not None
        line = self.client.stdout.readline().strip()
        if line != "connected":
            self.stop()
            raise RuntimeError(f"the Foxglove client did not connect: {line!r}")

    def cpu(self) -> tuple[float, float]:
        return _cpu_s(self.service.pid), _cpu_s(self.client.pid)

    def stop(self) -> None:
        client = getattr(self, "client", None)
        if client is not None:
            os.kill(client.pid, signal.SIGCONT)
            client.kill()
            client.wait()
        self.service.send_signal(signal.SIGINT)
        try:
            self.service.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.service.kill()
            self.service.wait()
        self.logs.write("".join("[foxglove] " + line for line in self.log_path.read_text().splitlines(True)))


def foxglove_numbers(
    window_s: float,
    rounds: int,
    port: int,
    ws_port: int,
    subscribe: str,
    logs: io.StringIO,
    client_nice: int = 10,
    settle_s: float = 3.0,
) -> dict:
    from services.launch.launcher import run_launch

    topics = sorted(layout_topics(json.loads(LAYOUT.read_text()))) if subscribe == "layout" else None
    result: dict = {"load_avg_1min_start": round(os.getloadavg()[0], 2), "window_s": window_s, "rounds": rounds,
                    "subscribe": subscribe, "client_nice": client_nice}  # fmt: skip
    per_round: list[dict] = []

    def hook(launcher, monitor) -> None:  # noqa: ANN001 - the launcher's hook
        stop = launcher.stop_event

        def window(server: Server | None) -> dict:
            with monitor.lock:
                a, b = len(monitor.delivery_ms), len(monitor.latencies_ms)
            cpu0, t0 = server.cpu() if server else (0.0, 0.0), time.monotonic()
            stop.wait(window_s)
            cpu1, dt = server.cpu() if server else (0.0, 0.0), time.monotonic() - t0
            with monitor.lock:
                deliv, lat = monitor.delivery_ms[a:], monitor.latencies_ms[b:]
            out = {"state_to_cmd_received": _percentiles(deliv), "state_to_cmd_published": _percentiles(lat)}
            if server:
                out["service_cpu_s_per_s"] = round((cpu1[0] - cpu0[0]) / dt, 3)
                out["client_cpu_s_per_s"] = round((cpu1[1] - cpu0[1]) / dt, 3)
            return out

        stop.wait(5.0)  # past the planner's first plans
        with tempfile.TemporaryDirectory(prefix="gpmppi-bench-foxglove-") as tmp:
            for r in range(rounds):
                if stop.is_set():
                    return
                numbers = {"off": window(None)}
                server = Server(port, ws_port, topics, client_nice, tmp, logs)
                try:
                    stop.wait(settle_s)  # the service's start (imports, first advertisements) outside the windows
                    order = ("connected", "client_stopped") if r % 2 == 0 else ("client_stopped", "connected")
                    for mode in order:
                        os.kill(server.client.pid, signal.SIGSTOP if mode == "client_stopped" else signal.SIGCONT)
                        numbers[mode] = window(server)
                finally:
                    server.stop()
                stop.wait(settle_s)
                per_round.append(numbers)

    code, summary = run_launch(None, port=port, out=logs, then=hook)
    result["per_round"] = per_round
    result["summary"] = summarize(per_round)
    result["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    result["exit_code"] = code
    result["restarts"] = summary.restarts
    return result


def summarize(per_round: list[dict]) -> dict:
    """Per mode: each round's state -> command received p99 [ms], and the off rounds' range (their spread), with how
    many of the other modes' rounds fall at or under the off rounds' largest p99."""
    p99 = {m: [r[m]["state_to_cmd_received"].get("p99_ms") for r in per_round] for m in MODES}
    out: dict = {"received_p99_ms_per_round": p99}
    off = [v for v in p99["off"] if v is not None]
    if off:
        out["off_p99_range_ms"] = [min(off), max(off)]
        out["off_p99_spread_ms"] = round(max(off) - min(off), 2)
        for m in MODES[1:]:
            values = [v for v in p99[m] if v is not None]
            out[f"{m}_p99_median_ms"] = round(float(np.median(values)), 2) if values else None
            out[f"{m}_rounds_within_off_range"] = f"{sum(v <= max(off) for v in values)}/{len(values)}"
    for m in MODES[1:]:
        cpu = [r[m].get("service_cpu_s_per_s") for r in per_round if m in r]
        out[f"{m}_service_cpu_s_per_s"] = round(float(np.mean(cpu)), 3) if cpu else None
    return out


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("foxglove")
    def bench_foxglove(
        window: float = typer.Option(8.0, min=0.5, max=3600.0, help="seconds per window"),
        rounds: int = typer.Option(3, min=1, max=1000, help="rounds of off / connected / stopped windows"),
        subscribe: str = typer.Option(
            "layout", help="what the client subscribes to: layout (the shipped layout's topics) or all"
        ),
        client_nice: int = typer.Option(
            10,
            min=0,
            max=19,
            help="the client's CPU priority (nice; the server's is 10): a client on the robot runs "
            "below the control path, as the server does; a laptop's costs the robot nothing",
        ),
        port: int = typer.Option(7465, min=1, max=65535, help="router port on 127.0.0.1"),
        ws_port: int = typer.Option(8766, min=1, max=65535, help="the Foxglove server's port on 127.0.0.1"),
        as_json: bool = typer.Option(False, "--json", help="print one JSON object instead of text"),
        show_logs: bool = typer.Option(False, help="print the services' logs too"),
    ) -> None:
        """The stack's state -> command latency with the Foxglove server off, on with a client, and that client
        stopped (SIGSTOP), in interleaved rounds; prints each mode's p99 per round and the off rounds' spread."""
        from tools.cli_checks import fail

        if subscribe not in ("layout", "all"):
            fail(f"--subscribe {subscribe}: not a choice; give layout or all")
        logs = io.StringIO()
        t0 = time.monotonic()
        try:
            result = foxglove_numbers(window, rounds, port, ws_port, subscribe, logs, client_nice)
        finally:
            if show_logs:
                typer.echo(logs.getvalue())
        result["wall_s"] = round(time.monotonic() - t0, 1)
        if as_json:
            typer.echo(json.dumps(result))
            return
        load = f"load avg {result['load_avg_1min_start']} -> {result['load_avg_1min_end']}"
        typer.echo(f"{load}, {rounds} rounds of {window:g} s windows, client: {subscribe}, nice {client_nice}")
        typer.echo("state -> command received, p50 / p99 [ms] (n); Foxglove service CPU [s/s]")
        for i, r in enumerate(result["per_round"]):
            cells = []
            for m in MODES:
                q = r[m]["state_to_cmd_received"]
                cpu = f", cpu {r[m]['service_cpu_s_per_s']:.3f}" if "service_cpu_s_per_s" in r[m] else ""
                cells.append(f"{m} {q.get('p50_ms')} / {q.get('p99_ms')} ({q['n']}){cpu}")
            typer.echo(f"  round {i + 1}: " + "; ".join(cells))
        s = result["summary"]
        if "off_p99_range_ms" in s:
            lo, hi = s["off_p99_range_ms"]
            typer.echo(f"off p99 over the rounds: {lo} .. {hi} ms (spread {s['off_p99_spread_ms']} ms)")
            for m in MODES[1:]:
                within = s[f"{m}_rounds_within_off_range"]
                median = s[f"{m}_p99_median_ms"]
                typer.echo(f"{m} p99: median {median} ms; at or under the off rounds' largest in {within}")
        typer.echo(f"exit code {result['exit_code']}, restarts {result['restarts']}, wall {result['wall_s']} s")
