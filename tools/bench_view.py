"""`gpmppi bench view` and `gpmppi bench viewer-stall`: the rerun view's cost.

- view: MCAP -> .rrd conversion speed (a multiple of real time) and .rrd bytes per minute of log for a 1-minute
  and a 5-minute run (their ratio shows whether the recording grows linearly). The logs are synthetic, with the
  demo stack's rates and message sizes, or a real recording tiled to length (`--log`).
- viewer-stall: the whole stack over Zenoh with the viewer; the viewer is stopped (SIGSTOP) and continued in
  turns, and the state -> command latency is compared between the windows (timings on a shared machine are noisy).
"""

from __future__ import annotations

import io
import json
import math
import os
import signal
import tempfile
import time
from pathlib import Path

import numpy as np
import typer

from tools.cli_checks import fail, only_with

# the demo stack's rates [Hz]: state, odom/raw, terrain/label, cmd, plan at the planner's 10 Hz, the base command
# at egress's 20 Hz, terrain weights about 7 Hz, one heartbeat a second from each of 7 services
RATES = {"state": 10.0, "base": 20.0, "weights": 7.0}
SERVICES = ("sim", "ingress", "terrain", "planner", "egress", "recorder", "viewer")


def synthetic_log(path: Path, duration_s: float, robot: str = "jackal", samples: int = 16, seed: int = 0) -> int:
    """Write a log of `duration_s` seconds as the demo stack records it (circle lane, plans with `samples`
    rollouts of 41 steps); returns the number of messages."""
    from schemas import BaseCommand, Command, Heartbeat, Plan, State, Task, TerrainLabel, TerrainWeights
    from services.recording.mcap_writer import McapWriter

    rng = np.random.default_rng(seed)
    radius, half_width, speed, dt, steps = 10.0, 1.75, 1.5, 0.1, 41
    a = np.linspace(0.0, 2 * np.pi, 200, endpoint=False)
    task = Task(kind="lane", centerline=np.stack([radius * np.cos(a), radius * np.sin(a)], 1).tolist(), closed=True)
    t0 = 1_700_000_000_000_000_000
    key = f"gpmppi/{robot}/{{}}"
    events: list[tuple[int, str, object]] = []
    n_state = int(duration_s * RATES["state"])
    for i in range(n_state):
        t = t0 + int(i * 1e8)
        phi = speed * i * dt / radius
        r = radius + 0.1 * np.sin(0.3 * i * dt)
        x, y, th = r * np.cos(phi), r * np.sin(phi), phi + np.pi / 2
        st = State(x=x, y=y, theta=math.atan2(math.sin(th), math.cos(th)), v=speed, omega=speed / radius)
        st.header.stamp_ns = t
        events += [
            (t, "odom/raw", st),
            (t + 2_000_000, "state", st),
            (t, "terrain/label", TerrainLabel(terrain="asphalt")),
        ]
        future = phi + speed * dt * np.arange(steps) / radius
        xs = np.stack([r * np.cos(future), r * np.sin(future), future, np.full(steps, speed), np.full(steps, 0.15)], 1)
        var = 1e-4 * np.arange(steps)
        smp = xs[None, :, :2] + rng.normal(0.0, 0.02, (samples, 1, 2)) * np.arange(steps)[None, :, None]
        cmd = Command(v_ref=speed, omega_ref=speed / radius)
        cmd.header.stamp_ns = t
        plan = Plan(
            command=cmd, controls=[[speed, speed / radius]] * (steps - 1), states=xs.tolist(),
            cov_xy=np.stack([var, 0 * var, var], 1).tolist(), tightened=(half_width - 3 * np.sqrt(var)).tolist(),
            samples=np.round(smp, 3).tolist(), sample_costs=rng.gamma(2.0, 200.0, samples).tolist(),
            terrain_weights=[0.6, 0.3, 0.1],
            timings_ms={"total": 6.0 + rng.gamma(2, 0.5), "rollouts": 4.0, "update": 0.2, "state_to_cmd": 15.0},
            critic_costs={"variance": 0.5, "deviation": 20.0 + rng.gamma(2.0, 2.0), "slip": 1.0, "lane_exit": 0.0,
                          "speed": 5.0, "collision": 0.0, "goal": 0.0, "terminal": 0.0},
            effective_samples=float(rng.uniform(1.0, samples)),
        )  # fmt: skip
        plan.header.stamp_ns, plan.header.seq = t, i
        st.header.seq = cmd.header.seq = i
        events += [(t + 15_000_000, "cmd", cmd), (t + 15_000_000, "plan", plan)]
    for i in range(int(duration_s * RATES["base"])):
        t = t0 + int(i * 5e7)
        bc = BaseCommand(v=speed, omega=speed / radius, reason="limit" if i % 7 == 0 else "planner")
        bc.header.stamp_ns = t
        events.append((t, "base/cmd", bc))
    for i in range(int(duration_s * RATES["weights"])):
        w = TerrainWeights(names=["asphalt", "grass", "tile"], weights=[0.6, 0.3, 0.1])
        w.header.stamp_ns = t0 + int(i * 1e9 / RATES["weights"])
        events.append((w.header.stamp_ns, "terrain/weights", w))
    for s in range(int(duration_s)):
        t = t0 + int(s * 1e9)
        task.header.stamp_ns = t
        events.append((t, "task", task.model_copy(deep=True)))
        for name in SERVICES:
            hb = Heartbeat(service=name, rate_hz=10.0, received=100 * s, published=100 * s)
            hb.header.stamp_ns, hb.header.seq = t, s
            events.append((t + 1000, f"health/{name}", hb))
    events.sort(key=lambda e: e[0])
    with McapWriter(path) as writer:
        for t, k, msg in events:
            writer.write(key.format(k), msg, log_time_ns=t)  # type: ignore[arg-type]
    return len(events)


def tiled_log(source: Path, path: Path, duration_s: float) -> int:
    """A real recording repeated (times shifted) to `duration_s` seconds; returns the number of messages."""
    from services.recording.mcap_io import read_messages
    from services.recording.mcap_writer import McapWriter

    msgs = list(read_messages(source))
    if not msgs:
        raise ValueError(f"{source} holds no readable messages")
    t_first, t_last = msgs[0][1], msgs[-1][1]
    span = max(t_last - t_first, 1) + 100_000_000
    n = 0
    with McapWriter(path) as writer:
        for rep in range(math.ceil(duration_s * 1e9 / span)):
            for key, log_ns, msg in msgs:
                shift = rep * span
                if log_ns - t_first + shift > duration_s * 1e9:
                    break
                m = msg.model_copy(deep=True)
                if m.header.stamp_ns:
                    m.header.stamp_ns += shift
                writer.write(key, m, log_time_ns=log_ns + shift)
                n += 1
    return n


def view_numbers(log: Path | None, minutes: list[float], samples: int) -> dict:
    from tools.replay_rerun import convert

    # the machine's 1-minute load average: conversion speed on a loaded machine is not that of an idle one
    out: dict = {"load_avg_1min": round(os.getloadavg()[0], 2), "runs": []}
    with tempfile.TemporaryDirectory(prefix="gpmppi-bench-view-") as tmp:
        for m in minutes:
            mcap = Path(tmp) / f"run_{m:g}min.mcap"
            n = tiled_log(log, mcap, m * 60) if log else synthetic_log(mcap, m * 60, samples=samples)
            rrd = Path(tmp) / f"run_{m:g}min.rrd"
            cpu0 = time.process_time()
            r = convert(mcap, "save", str(rrd))
            cpu_s = time.process_time() - cpu0  # all of this process's threads (rerun encodes on its own)
            size = rrd.stat().st_size
            out["runs"].append({
                "minutes": m, "messages": n, "mcap_bytes": mcap.stat().st_size, "rrd_bytes": size,
                "rrd_bytes_per_min": round(size / m), "convert_wall_s": r["wall_s"],
                "speed_x_real_time": round(r["log_duration_s"] / r["wall_s"], 1),
                # log seconds per CPU second: what an unloaded core would do (the wall figure depends on the load)
                "convert_cpu_s": round(cpu_s, 2), "speed_x_real_time_per_cpu": round(r["log_duration_s"] / cpu_s, 1),
            })  # fmt: skip
    runs = out["runs"]
    if len(runs) >= 2:
        # linear growth: bytes per minute stay the same (ratio ~1); a path re-logged whole would grow ~minutes
        out["bytes_per_min_ratio_last_to_first"] = round(
            runs[-1]["rrd_bytes_per_min"] / runs[0]["rrd_bytes_per_min"], 3
        )
    return out


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


def parse_minutes(text: str) -> list[float]:
    """'1,5' -> [1.0, 5.0]; UserError naming --minutes for anything but positive finite numbers."""
    try:
        values = [float(m) for m in text.split(",")]
    except ValueError:
        values = []
    if not values or not all(math.isfinite(v) and 0 < v <= 600 for v in values):
        fail(f"--minutes {text!r}: expected run lengths in minutes, comma-separated, each in (0, 600], e.g. 1,5")
    return values


def register(bench_app: typer.Typer) -> None:
    @bench_app.command("view")
    def bench_view(
        log: Path | None = typer.Option(None, help="tile this recording to length (default: a synthetic demo log)"),
        minutes: str = typer.Option("1,5", help="run lengths [min], comma-separated"),
        samples: int = typer.Option(
            16, min=0, max=4096, help="rollouts per plan in the synthetic log (the planner's default)"
        ),
        as_json: bool = typer.Option(False, "--json", help="print one JSON object instead of text"),
    ) -> None:
        """MCAP -> .rrd conversion speed (x real time) and .rrd bytes per minute for 1- and 5-minute runs."""
        result = view_numbers(log, parse_minutes(minutes), samples)
        if as_json:
            typer.echo(json.dumps(result))
            return
        typer.echo(f"load average (1 min) at start: {result['load_avg_1min']}")
        for r in result["runs"]:
            typer.echo(
                f"{r['minutes']:>4g} min: {r['messages']} messages, mcap {r['mcap_bytes'] / 1e6:.2f} MB, rrd "
                f"{r['rrd_bytes'] / 1e6:.2f} MB = {r['rrd_bytes_per_min'] / 1e6:.3f} MB/min; converted in "
                f"{r['convert_wall_s']:.2f} s = {r['speed_x_real_time']}x real time ({r['convert_cpu_s']:.2f} CPU s = "
                f"{r['speed_x_real_time_per_cpu']}x per CPU second)"
            )
        if "bytes_per_min_ratio_last_to_first" in result:
            typer.echo(
                f"bytes/min ratio (longest / shortest run): {result['bytes_per_min_ratio_last_to_first']} (1 = linear)"
            )

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
