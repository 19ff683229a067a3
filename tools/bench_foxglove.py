"""`gpmppi bench foxglove`: the simulated stack's state -> command latency with the Foxglove server off, on with a
client connected, and with that client stopped (SIGSTOP), in the manner of `gpmppi bench viewer-stall --mode stack`.

Two launches of the default stack: one without the Foxglove server (`off`), one with `--foxglove` where a WebSocket
client (its own process, subscribed to every channel and reading as fast as it can) is connected and then stopped
and continued in turns (`connected` / `client_stopped`). The latency is the launcher monitor's: state stamp ->
command received by the launcher's session, and the planner's own state -> command published.
"""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np
import typer

# the client: connects with Foxglove's WebSocket protocol, subscribes to every channel advertised, reads forever
CLIENT = r"""
import json, sys
from websockets.sync.client import connect
with connect(sys.argv[1], subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"], open_timeout=30) as ws:
    print("connected", flush=True)
    while True:
        frame = ws.recv()
        if isinstance(frame, str):
            msg = json.loads(frame)
            if msg.get("op") == "advertise":
                subs = [{"id": c["id"], "channelId": c["id"]} for c in msg["channels"]]
                ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
"""


def _percentiles(values: list[float]) -> dict:
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return {"n": 0}
    return {"n": int(a.size), "p50_ms": round(float(np.percentile(a, 50)), 2),
            "p99_ms": round(float(np.percentile(a, 99)), 2), "max_ms": round(float(a.max()), 2)}  # fmt: skip


def foxglove_numbers(window_s: float, windows: int, port: int, ws_port: int, logs: io.StringIO) -> dict:
    from services.launch.launcher import run_launch

    result: dict = {"load_avg_1min_start": round(os.getloadavg()[0], 2), "window_s": window_s}
    spans: dict[str, list[tuple[int, int, int, int]]] = {"off": [], "connected": [], "client_stopped": []}
    monitors: list = []

    def measure(monitor, phase: str, stop) -> None:  # noqa: ANN001 - the launcher's monitor and stop event
        with monitor.lock:
            a, b = len(monitor.delivery_ms), len(monitor.latencies_ms)
        stop.wait(window_s)
        with monitor.lock:
            spans[phase].append((a, len(monitor.delivery_ms), b, len(monitor.latencies_ms)))

    def server_off(launcher, monitor) -> None:  # noqa: ANN001 - the launcher's hook
        launcher.stop_event.wait(5.0)  # past the planner's first plans
        for _ in range(windows):
            measure(monitor, "off", launcher.stop_event)
        monitors.append(("off", monitor))

    def server_on(launcher, monitor) -> None:  # noqa: ANN001 - the launcher's hook
        client = subprocess.Popen(
            [sys.executable, "-c", CLIENT, f"ws://127.0.0.1:{ws_port}"],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        try:
            assert client.stdout is not None
            line = client.stdout.readline().decode().strip()
            if line != "connected":
                raise RuntimeError(f"the Foxglove client did not connect: {line!r}")
            launcher.stop_event.wait(5.0)
            for _ in range(windows):
                os.kill(client.pid, signal.SIGCONT)
                measure(monitor, "connected", launcher.stop_event)
                os.kill(client.pid, signal.SIGSTOP)
                measure(monitor, "client_stopped", launcher.stop_event)
            os.kill(client.pid, signal.SIGCONT)
        finally:
            os.kill(client.pid, signal.SIGCONT)
            client.kill()
            client.wait()
        monitors.append(("on", monitor))

    with tempfile.TemporaryDirectory(prefix="gpmppi-bench-foxglove-"):
        code_off, _ = run_launch(None, port=port, out=logs, then=server_off)
        code_on, summary = run_launch(None, port=port, out=logs, then=server_on, foxglove=("127.0.0.1", ws_port))
    by_run = dict(monitors)
    for phase, parts in spans.items():
        mon = by_run["off" if phase == "off" else "on"]
        deliv = [x for a, b, _, _ in parts for x in mon.delivery_ms[a:b]]
        lat = [x for _, _, c, d in parts for x in mon.latencies_ms[c:d]]
        result[phase] = {"state_to_cmd_received": _percentiles(deliv), "state_to_cmd_published": _percentiles(lat)}
    result["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    result["exit_codes"] = [code_off, code_on]
    result["restarts_with_foxglove"] = summary.restarts
    return result


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("foxglove")
    def bench_foxglove(
        window: float = typer.Option(8.0, min=0.5, max=3600.0, help="seconds per window"),
        windows: int = typer.Option(2, min=1, max=1000, help="windows per phase (connected and stopped alternate)"),
        port: int = typer.Option(7465, min=1, max=65535, help="router port on 127.0.0.1"),
        ws_port: int = typer.Option(8766, min=1, max=65535, help="the Foxglove server's port on 127.0.0.1"),
        as_json: bool = typer.Option(False, "--json", help="print one JSON object instead of text"),
        show_logs: bool = typer.Option(False, help="print the services' logs too"),
    ) -> None:
        """The stack's state -> command latency with the Foxglove server off, on with a client, and that client
        stopped (SIGSTOP)."""
        logs = io.StringIO()
        t0 = time.monotonic()
        try:
            result = foxglove_numbers(window, windows, port, ws_port, logs)
        finally:
            if show_logs:
                typer.echo(logs.getvalue())
        result["wall_s"] = round(time.monotonic() - t0, 1)
        if as_json:
            typer.echo(json.dumps(result))
            return
        for k, v in result.items():
            typer.echo(f"{k:>22}: {v}")
