"""The launcher's view of a run: an outside Zenoh client on `gpmppi/**`, and the end-of-run summary
(task result, planner rate and latency, messages per key, restarts, start-up times)."""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import zenoh

from schemas import (
    BaseCommand,
    Command,
    DecodeError,
    Heartbeat,
    Plan,
    State,
    Task,
    TerrainWeights,
    decode,
    model_for_key,
)
from services.runtime.node_settings import ZenohSettings
from services.runtime.session import open_session

if TYPE_CHECKING:
    from services.launch.processes import RestartEvent
    from services.launch.supervisor import Launcher


# the key each service's first real output appears on (start-up time is measured to it)
PRIMARY_OUTPUT = {
    "sim": "odom/raw",
    "ingress": "state",
    "terrain": "terrain/weights",
    "planner": "cmd",
    "egress": "base/cmd",
}


class Monitor:
    """Counts every key and keeps what the summary needs; opens its own client session."""

    def __init__(
        self, robot: str, zenoh_settings: ZenohSettings, t_start: float, stop: threading.Event | None = None
    ) -> None:
        self.robot = robot
        self.t_start = t_start
        self.lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.first_seen_s: dict[str, float] = {}
        self.heartbeats: dict[str, Heartbeat] = {}
        self.states: list[tuple[int, float, float]] = []
        self.latencies_ms: list[float] = []  # state stamp -> command published (the planner's own measure)
        self.delivery_ms: list[float] = []  # state stamp -> command received here
        self.plan_total_ms: list[float] = []
        self.task: Task | None = None
        self.undecodable = 0
        # every message on a service's primary output key: (monotonic arrival time, header seq); the seq starts
        # at 0 in each new process, which tells a restarted service's first output from its predecessor's last
        self.output_keys = {f"gpmppi/{robot}/{key}" for key in PRIMARY_OUTPUT.values()}
        self.output_arrivals: dict[str, list[tuple[float, int]]] = {key: [] for key in self.output_keys}
        # the last payload on each key, for the launcher to hand to the next process of a service (`last_payload`)
        self._last: dict[str, bytes] = {}
        # every command's (arrival, source): which process commanded when (`Command.source`)
        self.command_sources: list[tuple[float, str]] = []
        # every base command: (arrival, v, omega, reason)
        self.base_commands: list[tuple[float, float, float, str]] = []
        # waits for the router as long as zenoh_settings.wait_for_router_s says (services start in any order)
        self.session = open_session(zenoh_settings, logging.getLogger("gpmppi.launch"), stop)
        self._sub = self.session.declare_subscriber("gpmppi/**", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        received_ns = time.time_ns()
        received = time.monotonic()
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        with self.lock:
            self.counts[key] += 1
            self.first_seen_s.setdefault(key, received - self.t_start)
            self._last[key] = payload
        try:
            model = model_for_key(key)
            if model not in (State, Command, Plan, Heartbeat, Task, TerrainWeights, BaseCommand):
                return
            msg = decode(model, payload)
        except (KeyError, DecodeError):
            with self.lock:
                self.undecodable += 1
            return
        with self.lock:
            if key in self.output_keys:
                self.output_arrivals[key].append((received, msg.header.seq))
            if isinstance(msg, Heartbeat):
                self.heartbeats[msg.service] = msg
            elif isinstance(msg, State) and key.endswith("/state"):
                self.states.append((msg.header.stamp_ns, msg.x, msg.y))
            elif isinstance(msg, Command) and key.endswith("/cmd"):
                self.delivery_ms.append((received_ns - msg.header.stamp_ns) / 1e6)
                self.command_sources.append((received, msg.source))
            elif isinstance(msg, BaseCommand):
                self.base_commands.append((received, msg.v, msg.omega, msg.reason))
            elif isinstance(msg, Plan):
                if "total" in msg.timings_ms:
                    self.plan_total_ms.append(msg.timings_ms["total"])
                if "state_to_cmd" in msg.timings_ms:
                    self.latencies_ms.append(msg.timings_ms["state_to_cmd"])
            elif isinstance(msg, Task):
                self.task = msg

    def last_payload(self, key: str) -> bytes | None:
        """The last payload received on `key`, or None."""
        with self.lock:
            return self._last.get(key)

    def close(self) -> None:
        try:
            self._sub.undeclare()
            self.session.close()
        except Exception:  # noqa: BLE001 - closing twice or after the router went away is harmless
            pass


@dataclass
class Summary:
    duration_s: float = 0.0
    task_kind: str = ""
    task_line: str = ""  # the task's outcome in one line (`TaskRun.outcome`)
    lane_rmse_mm: float | None = None
    lane_exits: int | None = None
    goal_reached: bool | None = None
    final_goal_distance_m: float | None = None
    distance_driven_m: float = 0.0
    planner_rate_hz: float | None = None
    latency_p50_ms: float | None = None
    latency_p99_ms: float | None = None
    delivery_p50_ms: float | None = None  # state stamp -> command received by the launcher's own session
    delivery_p99_ms: float | None = None
    plan_p99_ms: float | None = None
    messages: dict[str, int] = field(default_factory=dict)
    heartbeats_from: list[str] = field(default_factory=list)
    first_heartbeat_s: dict[str, float] = field(default_factory=dict)  # service -> s from its process start
    first_output_s: dict[str, float] = field(default_factory=dict)  # service -> s from process start to output
    restarts: dict[str, int] = field(default_factory=dict)
    restart_events: list[RestartEvent] = field(default_factory=list)  # every crash restart, with its cause
    spare_events: list[str] = field(default_factory=list)  # every spare that died
    spares: dict[str, int] = field(default_factory=dict)  # service -> pid of its warm spare at the end
    failed: list[str] = field(default_factory=list)
    recording: str | None = None
    rerun_file: str | None = None  # the .rrd written (`--rerun save`)
    notes: list[str] = field(default_factory=list)  # why an output file is not the path given (it existed, ...)

    def lines(self) -> list[str]:
        out = [f"duration {self.duration_s:.1f} s, driven {self.distance_driven_m:.1f} m"]
        out.append(f"task: {self.task_line}" if self.task_line else "task: no task or no states seen")
        out.append(
            f"planner: {_fmt(self.planner_rate_hz, 'Hz')}; state stamp -> command published p50 "
            f"{_fmt(self.latency_p50_ms, 'ms')} p99 {_fmt(self.latency_p99_ms, 'ms')}; plan compute p99 "
            f"{_fmt(self.plan_p99_ms, 'ms')}; command received here p50 {_fmt(self.delivery_p50_ms, 'ms')} "
            f"p99 {_fmt(self.delivery_p99_ms, 'ms')}"
        )
        out.append("messages per key:")
        out += [f"  {k}: {n}" for k, n in sorted(self.messages.items())]
        out.append(f"heartbeats from: {', '.join(sorted(self.heartbeats_from)) or 'none'}")
        starts = ", ".join(f"{k} {v:.2f}" for k, v in sorted(self.first_output_s.items()))
        out.append(f"start-up, process start -> first output [s]: {starts or 'n/a'}")
        out.append(f"restarts: {self.restarts or 'none'}; failed for good: {self.failed or 'none'}")
        for e in self.restart_events:
            note = f"; {e.note}" if e.note else ""
            how = (f"its warm spare (pid {e.takeover_pid}) took over after {e.delay_s:.3f} s"
                   if e.takeover_pid is not None else f"restarted after {e.delay_s:.2f} s")
            out.append(f"  {e.name}: {e.cause} at {e.died_s:.1f} s after {e.uptime_s:.1f} s up, {how}{note}")
        spares = ", ".join(f"{k} (pid {v})" for k, v in sorted(self.spares.items()))
        out.append(f"warm spares at the end: {spares or 'none'}")
        out += [f"  {e}" for e in self.spare_events]
        if self.recording:
            out.append(f"recording: {self.recording}")
        if self.rerun_file:
            out.append(f"rerun: {self.rerun_file}")
        out += self.notes
        return out


def _fmt(v: float | None, unit: str) -> str:
    return "n/a" if v is None else f"{v:.1f} {unit}"


def summarize(monitor: Monitor | None, launcher: Launcher, service_names: list[str], record: str | None) -> Summary:
    s = Summary(duration_s=time.monotonic() - launcher.t0, recording=record)
    s.restarts = {c.name: c.restarts for c in launcher.children if c.restarts}
    s.restart_events = list(launcher.restart_events)
    s.spare_events = list(launcher.spare_events)
    s.spares = dict(launcher.spares_at_stop)
    s.failed = [c.name for c in launcher.children if c.failed]
    if monitor is None:
        return s
    with monitor.lock:
        s.messages = dict(monitor.counts)
        s.heartbeats_from = sorted(monitor.heartbeats)
        first_seen = dict(monitor.first_seen_s)
        states = np.array([[x, y] for _, x, y in sorted(monitor.states)]).reshape(-1, 2)
        task = monitor.task
        latencies = np.array(monitor.latencies_ms)
        delivery = np.array(monitor.delivery_ms)
        plan_ms = np.array(monitor.plan_total_ms)
        planner_hb = monitor.heartbeats.get("planner")
    started = {c.name: c.first_started_at - monitor.t_start for c in launcher.children}
    prefix = f"gpmppi/{monitor.robot}/"
    for key, t in first_seen.items():
        if key.startswith(prefix + "health/") and key[len(prefix + "health/") :] in started:
            name = key[len(prefix + "health/") :]
            s.first_heartbeat_s[name] = t - started[name]
    for name, key in PRIMARY_OUTPUT.items():
        if name in started and prefix + key in first_seen:
            s.first_output_s[name] = first_seen[prefix + key] - started[name]
    if record and Path(record).is_file():
        states, task, s.messages = _from_recording(record, monitor.robot, states, task)
    if latencies.size:
        s.latency_p50_ms = float(np.percentile(latencies, 50))
        s.latency_p99_ms = float(np.percentile(latencies, 99))
    if delivery.size:
        s.delivery_p50_ms = float(np.percentile(delivery, 50))
        s.delivery_p99_ms = float(np.percentile(delivery, 99))
    if plan_ms.size:
        s.plan_p99_ms = float(np.percentile(plan_ms, 99))
    if planner_hb is not None:
        s.planner_rate_hz = planner_hb.rate_hz
    if states.shape[0] > 1:
        s.distance_driven_m = float(np.sum(np.linalg.norm(np.diff(states, axis=0), axis=1)))
    if task is not None and states.shape[0]:
        score_task(s, task, states)
    return s


def score_task(s: Summary, task: Task, states: np.ndarray) -> None:
    """The task's outcome from the driven positions, as its kind's evaluation gives it (`TaskRun.outcome`)."""
    from gpmppi.evaluation.task_runs import run_for
    from services.codec.convert import task_from_message

    s.task_kind = task.kind
    scores, s.task_line = run_for(task_from_message(task)).outcome(states)
    for name, value in scores.items():
        setattr(s, name, value)


def _from_recording(
    record: str, robot: str, states: np.ndarray, task: Task | None
) -> tuple[np.ndarray, Task | None, dict[str, int]]:
    from services.recording.mcap_io import read_messages

    counts: Counter[str] = Counter()
    rec_states: list[tuple[int, float, float]] = []
    rec_task = None
    for key, _, msg in read_messages(record):
        counts[key] += 1
        if isinstance(msg, State) and key == f"gpmppi/{robot}/state":
            rec_states.append((msg.header.stamp_ns, msg.x, msg.y))
        elif isinstance(msg, Task):
            rec_task = msg
    if rec_states:
        states = np.array([[x, y] for _, x, y in sorted(rec_states)])
    return states, rec_task or task, dict(counts)
