"""`gpmppi bench view`: the rerun view's cost (a stopped viewer's effect on the control path: `gpmppi bench
viewer-stall`, tools.bench_viewer_stall).

- view: MCAP -> .rrd conversion speed (a multiple of real time) and .rrd bytes per minute of log for a 1-minute
  and a 5-minute run (their ratio shows whether the recording grows linearly). The logs are synthetic, with the
  demo stack's rates and message sizes, or a real recording tiled to length (`--log`).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import typer

from tools.cli_checks import fail

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
