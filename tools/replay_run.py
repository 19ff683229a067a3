"""Running one `gpmppi replay` onto Zenoh (`run_replay`, from a `ReplayRequest`): the router and the live services
that replace recorded ones, the player with its progress, and the comparison of the live commands with the recorded
ones. The command's options, checks and printing are `tools.replay`."""

from __future__ import annotations

import json
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tools.replay_live import ReplaceError


@dataclass
class ReplayRequest:
    log: Path
    speed: float = 1.0
    start_s: float | None = None
    end_s: float | None = None
    keys: str | None = None
    exclude: str | None = None
    loop: bool = False
    robot: str | None = None
    keep_stamps: bool = False
    replace: str | None = None
    sets: list[str] = field(default_factory=list)
    configs: list[str] = field(default_factory=list)
    compare: bool = False
    connect: str | None = None
    port: int | None = None
    delay_s: float = 0.5
    ready_timeout_s: float = 600.0
    settle_s: float = 1.0
    progress: bool = True
    lockstep: bool = False
    foxglove: tuple[str, int] | None = None
    profile: Path | None = None  # the robot profile the replaced planner and terrain services run with


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class _ReplayPlan:
    """What one replay does, worked out and checked from the request and the log before anything starts."""

    parts: Any  # the log's checked parts (`services.recording.player_log.check_log`)
    keys: list[str]  # the recorded channels
    span: tuple[int, int] | None  # the log's first and last log time [ns]
    robot: str  # the robot the replay publishes as
    live: list[Any]  # the live services that replace recorded ones (`tools.replay_live.LiveService`)
    planners: list[Any]  # the live planners among them
    endpoint: str  # the router the replay publishes to
    start_router: bool  # whether the replay starts that router
    options: Any  # the player's options (`services.recording.player.PlayOptions`)
    recorded_cmds: dict[int, tuple[float, float]]  # with --compare: the recorded commands by state stamp [ns]


def _plan_replay(req: ReplayRequest) -> _ReplayPlan:
    """The replay's plan; raises LogError / ReplaceError / ValueError for bad input, before anything is started."""
    from services.recording.player import PlayOptions
    from services.recording.player_log import (
        LogError,
        check_log,
        keys_and_services,
        log_span_ns,
        read_run_info,
        robots_in,
    )
    from services.runtime.node_settings import DEFAULT_ROUTER
    from tools import replay_live as rl

    parts = check_log(req.log)
    keys, logged_services = keys_and_services(parts)
    if not keys:
        raise LogError(f"{req.log} holds no messages (no channels): nothing to replay")
    robots = robots_in(keys)
    recorded_robot = robots[0] if robots else "jackal"
    info = read_run_info(parts)
    if info.run.get("robot"):
        recorded_robot = info.run["robot"]
    robot = req.robot or recorded_robot
    names = rl.parse_replace(req.replace) if req.replace else []
    if (req.sets or req.configs) and not names:
        raise ReplaceError("--set / --config change the settings of replaced services: add --replace SERVICE")
    if req.compare and not any(n for n in names):
        raise ReplaceError("--compare compares a live planner with the recorded one: add --replace planner")
    if req.lockstep and not req.compare:
        raise ReplaceError("--lockstep paces the states by the live planner's answers: it needs --compare")
    live = rl.live_services(names, info, logged_services, robot, _say)
    rl.apply_overrides(live, req.configs, req.sets)
    planners = [s for s in live if s.kind == "planner"]
    if req.compare and not planners:
        raise ReplaceError("--compare compares commands (cmd): it needs a planner among --replace")
    start_router = ((bool(live) or req.foxglove is not None) and req.connect is None) or req.port is not None
    if req.connect is not None:
        endpoint = req.connect
    elif start_router:
        endpoint = f"tcp/127.0.0.1:{req.port or _free_port()}"
    else:
        endpoint = DEFAULT_ROUTER  # where `gpmppi launch` and the services look by default
    rl.finalize(live, info, robot, endpoint, rl.temp_dir(), req.profile)

    def rkey(rel: str) -> str:
        return f"gpmppi/{recorded_robot}/{rel}"

    suppress: set[str] = set()
    for s in live:
        suppress |= {rkey(k) for k in rl.OUTPUTS[s.kind]} | {rkey(f"health/{s.name}")}
    start_s = req.start_s
    recorded_cmds: dict[int, tuple[float, float]] = {}
    if req.compare:
        recorded_cmds = _recorded_commands(parts, rkey("cmd"))
        if start_s is None:
            start_s = _first_answered_state_s(parts, rkey("state"), min(recorded_cmds))
    options = PlayOptions(
        speed=req.speed, start_s=start_s, end_s=req.end_s, keys=req.keys, exclude=req.exclude, loop=req.loop,
        robot=req.robot, keep_stamps=req.keep_stamps, suppress=suppress,
        prime={rkey(k) for k in ("task", "terrain/weights", "estop")} if start_s else set(),
        track_key=rkey("state"),
        # compared: only the states the recorded planner answered (those it skipped, being busy, had no effect on it)
        only_stamps=set(recorded_cmds) if req.compare else None,
        lockstep_timeout_s=2.0 if req.lockstep else None,
    )
    return _ReplayPlan(parts, keys, log_span_ns(parts), robot, live, planners, endpoint, start_router, options,
                       recorded_cmds)


def _recorded_commands(parts: Any, cmd_key: str) -> dict[int, tuple[float, float]]:
    """The recorded planner's commands (v_ref, omega_ref) by the stamp of the state each answered [ns]."""
    from services.recording.player_log import iter_records

    cmds: dict[int, tuple[float, float]] = {}
    for rec in iter_records(parts):
        if rec.key == cmd_key:
            m = json.loads(rec.data)
            cmds[int(m["header"]["stamp_ns"])] = (float(m["v_ref"]), float(m["omega_ref"]))
    if not cmds:
        raise ReplaceError(f"--compare: the recording has no commands on {cmd_key} to compare with")
    return cmds


def _first_answered_state_s(parts: Any, state_key: str, first_cmd: int) -> float | None:
    """Where in the log [s] the state the recorded planner's first command answered was logged (None: not found).
    The live planner starts from that state (and the newest weights before it), so both plan the same states from
    the same start."""
    from services.recording.player_log import iter_records

    log_t0 = None
    for rec in iter_records(parts):
        log_t0 = rec.log_time_ns if log_t0 is None else log_t0
        if rec.key == state_key and json.loads(rec.data)["header"]["stamp_ns"] == first_cmd:
            start_s = max(0.0, (rec.log_time_ns - log_t0 - 1000) / 1e9)
            _say(f"replay: comparing from the state of the recorded planner's first command, {start_s:.3f} s "
                 "into the log (give --start to choose)")
            return start_s
    return None


def _start_services(req: ReplayRequest, plan: _ReplayPlan) -> Any:
    """The router and live services the replay needs, started (a `Launcher`, or None where it needs neither: then a
    router must already listen at the plan's endpoint)."""
    from services.launch.launch_file import LaunchFile
    from services.launch.processes import wait_for_endpoint
    from services.launch.supervisor import Launcher

    if not (plan.start_router or plan.live or req.foxglove is not None):
        try:
            wait_for_endpoint(plan.endpoint, timeout_s=3.0)
        except TimeoutError:
            raise TimeoutError(f"no router at {plan.endpoint}: start the stack (gpmppi launch), pass --connect "
                               "ENDPOINT, or --port N to start a router for the replay") from None
        return None
    launch = LaunchFile(robot=plan.robot)
    launch.router.listen = [plan.endpoint]
    launcher = Launcher(launch, out=sys.stderr)
    try:
        if plan.start_router:
            launcher.add("router", "router", {"listen": [plan.endpoint]}, required=True)
        for s in plan.live:
            launcher.add(s.name, s.kind, s.config, required=True)
            _say(f"replay: live {s.name} ({s.kind}) from the "
                 f"{'recorded settings' if s.from_metadata else 'defaults'}; its recorded outputs are not replayed")
        if req.foxglove is not None:  # served to Foxglove as it plays, like `gpmppi launch --foxglove`
            zenoh_cfg = {"mode": "client", "connect": [plan.endpoint]}
            launcher.add("foxglove", "foxglove", {"robot": plan.robot, "zenoh": zenoh_cfg, "host": req.foxglove[0],
                                                  "port": req.foxglove[1], "nice": 10}, required=False)
        launcher.start_all()
    except BaseException:
        launcher.stop_all()
        raise
    return launcher


class _LiveCommands:
    """The live planners' commands as they arrive on Zenoh's thread: (state stamp [ns], v_ref, omega_ref)."""

    def __init__(self) -> None:
        self.got: list[tuple[int, float, float]] = []
        self._lock = threading.Condition()

    def on_cmd(self, sample: Any) -> None:
        try:
            m = json.loads(sample.payload.to_bytes())
            with self._lock:
                self.got.append((int(m["header"]["stamp_ns"]), float(m["v_ref"]), float(m["omega_ref"])))
                self._lock.notify_all()
        except (ValueError, KeyError, TypeError):
            pass

    def answered(self, stamp: int, timeout_s: float) -> bool:
        """Whether a live planner answered the state stamped `stamp` within `timeout_s` (the lockstep's pacing)."""
        with self._lock:
            return self._lock.wait_for(lambda: any(c[0] == stamp for c in self.got[-8:]), timeout_s)

    def snapshot(self) -> list[tuple[int, float, float]]:
        with self._lock:
            return list(self.got)


def run_replay(req: ReplayRequest, stop: threading.Event | None = None) -> dict[str, Any]:
    """Replay `req.log`; returns {"play": stats, "compare": {...} (with --compare), "services": [...]}.
    Raises LogError / ReplaceError / ValueError for bad input, before anything is started."""
    import zenoh

    from services.recording.player import Player, copy_payloads, drain
    from services.recording.player_log import iter_records
    from services.runtime.node_settings import ZenohSettings
    from tools import replay_live as rl

    plan = _plan_replay(req)
    stop = stop or threading.Event()
    result: dict[str, Any] = {"services": [s.name for s in plan.live]}
    launcher = _start_services(req, plan)
    session: zenoh.Session | None = None
    helper: zenoh.Session | None = None
    try:
        session = zenoh.open(copy_payloads(ZenohSettings(mode="client", connect=[plan.endpoint]).to_config()))
        helper = zenoh.open(ZenohSettings(mode="client", connect=[plan.endpoint]).to_config())
        live_cmds = _LiveCommands()
        subs = [session.declare_subscriber(f"gpmppi/{plan.robot}/cmd", live_cmds.on_cmd)] if plan.planners else []
        waiting = [*plan.live,
                   *([rl.LiveService("foxglove", "foxglove", {}, False)] if req.foxglove is not None else [])]
        if waiting:
            _wait_ready(session, plan.robot, waiting, launcher, req.ready_timeout_s, stop)
        time.sleep(req.delay_s)  # subscriptions of listeners that just joined reach the router
        player = Player(session, lambda: iter_records(plan.parts), plan.options, stop=stop)
        player.declare(plan.keys)
        player.answered = live_cmds.answered
        total_s = None if plan.span is None else (plan.span[1] - plan.span[0]) / 1e9
        if req.end_s is not None:
            total_s = req.end_s if total_s is None else min(total_s, req.end_s)
        stats = _play_with_progress(player, total_s, req.progress)
        if not drain(session, helper):
            _say("replay: warning: the router did not confirm it took every message within 60 s; some may be lost")
        result["play"] = stats
        if plan.live and not stop.is_set():
            time.sleep(req.settle_s)  # the live services' answers to the last inputs
        for sub in subs:
            sub.undeclare()
        if req.compare:
            got = live_cmds.snapshot()
            result["compare"] = rl.compare(got, plan.recorded_cmds, None if req.keep_stamps else player.stamp_map)
            result["compare"]["live_commands"] = len(got)
            if req.lockstep:
                result["compare"]["lockstep_misses"] = player.lockstep_misses
                result["compare"]["lockstep_shifts"] = stats.lockstep_shifts
    finally:
        if session is not None:
            session.close()
        if helper is not None:
            helper.close()
        if launcher is not None:
            launcher.stop_all()
    return result


def _wait_ready(session: Any, robot: str, live: list, launcher: Any, timeout_s: float, stop: threading.Event) -> None:
    """Wait for a heartbeat of every live service (the planner's comes after its kernels are compiled/loaded)."""
    seen: set[str] = set()
    subs = [session.declare_subscriber(f"gpmppi/{robot}/health/{s.name}", lambda _, n=s.name: seen.add(n))
            for s in live]
    deadline = time.monotonic() + timeout_s
    try:
        while len(seen) < len(live):
            for child in launcher.children:
                if child.process is not None and child.process.poll() is not None:
                    raise RuntimeError(f"live {child.name} exited with {child.process.returncode} before it was up "
                                       "(its log is above)")
            if time.monotonic() > deadline:
                raise TimeoutError(f"live services not up after {timeout_s:.0f} s: "
                                   f"{', '.join(s.name for s in live if s.name not in seen)}")
            if stop.wait(0.05):
                return
    finally:
        for sub in subs:
            sub.undeclare()


def _play_with_progress(player: Any, total_s: float | None, show: bool) -> Any:
    if not show:
        return player.play()
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    columns = [TextColumn("replay"), BarColumn(), TextColumn("{task.completed:.1f} / {task.fields[total_text]} s log"),
               TimeElapsedColumn()]
    with Progress(*columns, console=Console(stderr=True), transient=False) as bar:
        task = bar.add_task("replay", total=total_s, total_text=f"{total_s:.1f}" if total_s else "?")
        player.on_progress = lambda log_s: bar.update(task, completed=log_s)
        stats = player.play()
        if total_s:
            bar.update(task, completed=min(total_s, (player.stats.log_span_s or 0) + (player.o.start_s or 0)))
    return stats
