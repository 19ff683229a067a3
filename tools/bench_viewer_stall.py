"""`gpmppi bench viewer-stall`: whether a stopped viewer delays the control path. The whole stack over Zenoh with
the viewer, or a state -> command echo with no planner compute (`transport_stall_numbers`); the viewer is stopped
(SIGSTOP) and continued in turns, and the state -> command latency is compared between the windows (timings on a
shared machine are noisy).
"""

from __future__ import annotations

import io
import json
import os
import signal
import tempfile
import time
from pathlib import Path

import numpy as np
import typer

from tools.cli_checks import only_with


def stall_numbers(duration_s: float, windows: int, port: int, logs: io.StringIO) -> dict:
    from services.launch.launcher import run_launch

    phases: list[tuple[str, int, int, int, int]] = []  # (phase, delivery from, to, planner-latency from, to)

    def alternate(launcher, monitor) -> None:  # noqa: ANN001 - the launcher's hook
        viewer = next(c for c in launcher.children if c.name == "viewer")
        time.sleep(5.0)  # past the planner's first plans
        for w in range(2 * windows):
            stopped = w % 2 == 1
            pid = viewer.process.pid
            os.kill(pid, signal.SIGSTOP if stopped else signal.SIGCONT)
            with monitor.lock:
                a, b = len(monitor.delivery_ms), len(monitor.latencies_ms)
            launcher.stop_event.wait(duration_s)
            with monitor.lock:
                phases.append(
                    ("stopped" if stopped else "running", a, len(monitor.delivery_ms), b, len(monitor.latencies_ms))
                )
            if launcher.stop_event.is_set():
                break
        os.kill(viewer.process.pid, signal.SIGCONT)
        nonlocal_monitor.append(monitor)

    nonlocal_monitor: list = []
    with tempfile.TemporaryDirectory(prefix="gpmppi-bench-stall-") as tmp:
        load_before = os.getloadavg()[0]
        code, summary = run_launch(
            None, rerun=["save", str(Path(tmp) / "view.rrd")], port=port, out=logs, then=alternate
        )
    if not nonlocal_monitor:
        raise RuntimeError("the run ended before the stall windows finished; see --show-logs")
    mon = nonlocal_monitor[0]
    result: dict = {"load_avg_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)], "window_s": duration_s}
    for phase in ("running", "stopped"):
        deliv = np.concatenate([mon.delivery_ms[a:b] for p, a, b, _, _ in phases if p == phase] or [np.zeros(0)])
        lat = np.concatenate([mon.latencies_ms[c:d] for p, _, _, c, d in phases if p == phase] or [np.zeros(0)])
        result[phase] = {
            "commands": int(deliv.size),
            "state_to_cmd_received_p50_ms": round(float(np.percentile(deliv, 50)), 2) if deliv.size else None,
            "state_to_cmd_received_p99_ms": round(float(np.percentile(deliv, 99)), 2) if deliv.size else None,
            "state_to_cmd_published_p50_ms": round(float(np.percentile(lat, 50)), 2) if lat.size else None,
            "state_to_cmd_published_p99_ms": round(float(np.percentile(lat, 99)), 2) if lat.size else None,
        }
    for k in ("state_to_cmd_received_p99_ms", "state_to_cmd_published_p99_ms"):
        a, b = result["running"][k], result["stopped"][k]
        result[k.replace("_ms", "_stopped_minus_running_ms")] = (
            round(b - a, 2) if a is not None and b is not None else None
        )
    result["exit_code"] = code
    result["restarts"] = summary.restarts
    return result


def _plan_payloads(n: int, samples: int) -> list[bytes]:
    from schemas import Command, Plan, encode

    rng = np.random.default_rng(0)
    out = []
    for _ in range(n):
        plan = Plan(
            command=Command(v_ref=1.0, omega_ref=0.0), controls=[[1.0, 0.0]] * 40,
            states=[[0.1 * k, 0.0, 0.0, 1.0, 0.0] for k in range(41)], cov_xy=[[1e-3, 0.0, 1e-3]] * 41,
            tightened=[1.7] * 41, samples=np.round(rng.normal(size=(samples, 41, 2)), 3).tolist(),
            sample_costs=[1.0] * samples,
        )  # fmt: skip
        out.append(encode(plan))
    return out


def transport_stall_numbers(
    window_s: float, windows: int, port: int, rate_hz: float, samples: int, drop_wait_us: int | None = None
) -> dict:
    """State -> command over Zenoh with no planner compute: a state is published (with its send time), an echo
    session answers each with a command, and the first session times the command's arrival; plans of `samples`
    rollouts flow alongside at the planner's 10 Hz. A real viewer service is subscribed to everything and is
    stopped (SIGSTOP) in every second window (each shorter than the 10 s session lease)."""
    import subprocess
    import sys
    import threading

    import yaml
    import zenoh

    from services.runtime.node_settings import ZenohSettings

    endpoint = f"tcp/127.0.0.1:{port}"
    config = zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    if drop_wait_us is not None:  # how long the router waits on a full queue (a stopped viewer's) before dropping
        for k in ("wait_before_drop", "max_wait_before_drop_fragments"):
            config.insert_json5(f"transport/link/tx/queue/congestion_control/drop/{k}", str(drop_wait_us))
    latencies: dict[int, float] = {}
    sent_at: dict[int, int] = {}
    lock = threading.Lock()
    with tempfile.TemporaryDirectory(prefix="gpmppi-bench-stall-") as tmp:
        cfg = Path(tmp) / "viewer.yaml"
        cfg.write_text(yaml.safe_dump({
            "service": "viewer", "robot": "bench", "mode": "save", "path": str(Path(tmp) / "v.rrd"),
            "zenoh": {"mode": "client", "connect": [endpoint]}, "nice": 10,
        }))  # fmt: skip
        rtr = zenoh.open(config)
        viewer = subprocess.Popen(
            [sys.executable, "-m", "services.run", "viewer", "--config", str(cfg)],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
        )  # fmt: skip
        zs = ZenohSettings(mode="client", connect=[endpoint]).to_config
        a, b = zenoh.open(zs()), zenoh.open(zs())
        try:
            cmd_pub = b.declare_publisher("gpmppi/bench/cmd")
            # the echo: each state is answered at once with a command carrying the state's number
            echo = b.declare_subscriber("gpmppi/bench/state", lambda s: cmd_pub.put(s.payload.to_bytes()))

            def on_cmd(sample: zenoh.Sample) -> None:
                now = time.perf_counter_ns()
                n = int(sample.payload.to_bytes())
                with lock:
                    if n in sent_at:
                        latencies[n] = (now - sent_at[n]) / 1e6

            cmd_sub = a.declare_subscriber("gpmppi/bench/cmd", on_cmd)
            state_pub = a.declare_publisher("gpmppi/bench/state")
            plan_pub = a.declare_publisher("gpmppi/bench/plan")
            plans = _plan_payloads(4, samples)
            deadline = time.monotonic() + 60
            while not (state_pub.matching_status.matching and cmd_pub.matching_status.matching):
                if time.monotonic() > deadline:
                    raise RuntimeError("the echo session did not match within 60 s")
                time.sleep(0.05)
            # the viewer is up, its subscriber declared, once it sends its first heartbeat (its imports and session
            # take seconds; a fixed wait could start the windows before it listens on a loaded machine)
            viewer_up = threading.Event()
            health = a.declare_subscriber("gpmppi/bench/health/viewer", lambda _: viewer_up.set())
            if not viewer_up.wait(60.0):
                raise RuntimeError(f"the viewer sent no heartbeat within 60 s (exit code {viewer.poll()})")
            health.undeclare()
            phases: list[tuple[str, int, int]] = []
            n = 0
            for w in range(2 * windows):
                stopped = w % 2 == 1
                os.kill(viewer.pid, signal.SIGSTOP if stopped else signal.SIGCONT)
                first = n
                end = time.monotonic() + window_s
                while time.monotonic() < end:
                    with lock:
                        sent_at[n] = time.perf_counter_ns()
                    state_pub.put(str(n).encode())
                    if n % max(1, int(rate_hz / 10)) == 0:
                        plan_pub.put(plans[n % len(plans)])
                    n += 1
                    time.sleep(1.0 / rate_hz)
                phases.append(("stopped" if stopped else "running", first, n))
            os.kill(viewer.pid, signal.SIGCONT)
            time.sleep(0.5)
            echo.undeclare()
            cmd_sub.undeclare()
        finally:
            os.kill(viewer.pid, signal.SIGCONT)
            viewer.send_signal(signal.SIGINT)
            try:
                viewer.wait(20)
            except subprocess.TimeoutExpired:
                viewer.kill()
            a.close()
            b.close()
            rtr.close()
    result: dict = {
        "load_avg_1min": round(os.getloadavg()[0], 2), "window_s": window_s, "state_hz": rate_hz,
        "router_drop_wait_us": drop_wait_us if drop_wait_us is not None else "zenoh default (1000, fragments 50000)",
    }  # fmt: skip
    for phase in ("running", "stopped"):
        ids = [i for p, lo, hi in phases if p == phase for i in range(lo, hi)]
        lat = np.array([latencies[i] for i in ids if i in latencies])
        result[phase] = {
            "states": len(ids), "commands_back": int(lat.size),
            "p50_ms": round(float(np.percentile(lat, 50)), 3) if lat.size else None,
            "p99_ms": round(float(np.percentile(lat, 99)), 3) if lat.size else None,
            "max_ms": round(float(lat.max()), 3) if lat.size else None,
        }  # fmt: skip
    r, s_ = result["running"]["p99_ms"], result["stopped"]["p99_ms"]
    result["p99_stopped_minus_running_ms"] = round(s_ - r, 3) if r is not None and s_ is not None else None
    # per pair of neighbouring windows (running, then stopped): the difference of their p99s. Its median is robust
    # to a burst of load from elsewhere on the machine landing in one window
    per_window = []
    for _, lo, hi in phases:
        lat = [latencies[i] for i in range(lo, hi) if i in latencies]
        per_window.append(float(np.percentile(lat, 99)) if lat else float("nan"))
    diffs = [per_window[k + 1] - per_window[k] for k in range(0, len(per_window) - 1, 2)]
    result["pair_p99_differences_ms"] = [round(d, 2) for d in diffs]
    result["median_pair_p99_difference_ms"] = round(float(np.median(diffs)), 3) if diffs else None
    return result


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("viewer-stall")
    def bench_viewer_stall(
        mode: str = typer.Option(
            "transport",
            help="transport: state -> command over Zenoh with an echo, no "
            "planner compute (low noise); stack: the whole simulated stack",
        ),
        window: float = typer.Option(
            8.0,
            min=0.5, max=3600.0,
            help="seconds per window (viewer running / stopped); under 10 s keeps "
            "the stopped viewer's session alive at the router",
        ),
        windows: int = typer.Option(3, min=1, max=1000, help="pairs of windows"),
        rate: float = typer.Option(100.0, min=0.1, max=100_000.0, help="transport mode: states per second"),
        samples: int = typer.Option(
            16, min=0, max=4096,
            help="transport mode: rollouts per plan (plans at 10 Hz; the planner sends 16)",
        ),
        port: int = typer.Option(7463, min=1, max=65535, help="router port on 127.0.0.1"),
        drop_wait_us: int | None = typer.Option(
            None, min=0,
            help="transport mode: the router's wait before dropping for a full queue [us] (default: zenoh's)"
        ),
        as_json: bool = typer.Option(False, "--json", help="print one JSON object instead of text"),
        show_logs: bool = typer.Option(False, help="stack mode: print the services' logs too"),
    ) -> None:
        """State -> command latency over Zenoh with the viewer running vs stopped (SIGSTOP), in turns."""
        only_with(mode == "transport", "--mode transport",
                  {"--rate": rate != 100.0, "--samples": samples != 16, "--drop-wait-us": drop_wait_us is not None})
        only_with(mode == "stack", "--mode stack", {"--show-logs": show_logs})
        if mode == "transport":
            result = transport_stall_numbers(window, windows, port, rate, samples, drop_wait_us)
        elif mode == "stack":
            logs = io.StringIO()
            try:
                result = stall_numbers(window, windows, port, logs)
            finally:
                if show_logs:
                    typer.echo(logs.getvalue())
        else:
            raise typer.BadParameter(f"--mode is transport or stack, not {mode!r}")
        if as_json:
            typer.echo(json.dumps(result))
        else:
            for k, v in result.items():
                typer.echo(f"{k:>30}: {v}")
