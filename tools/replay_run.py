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


def run_replay(req: ReplayRequest, stop: threading.Event | None = None) -> dict[str, Any]:
    """Replay `req.log`; returns {"play": stats, "compare": {...} (with --compare), "services": [...]}.
    Raises LogError / ReplaceError / ValueError for bad input, before anything is started."""
    import zenoh

    from services.launch.launch_file import LaunchFile
    from services.launch.processes import wait_for_endpoint
    from services.launch.supervisor import Launcher
    from services.recording.player import Player, PlayOptions, copy_payloads, drain
    from services.recording.player_log import (
        LogError,
        check_log,
        iter_records,
        keys_and_services,
        log_span_ns,
        read_run_info,
        robots_in,
    )
    from services.runtime.node_settings import DEFAULT_ROUTER, ZenohSettings
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
    tmp = rl.temp_dir()
    rl.finalize(live, info, robot, endpoint, tmp, req.profile)

    def rkey(rel: str, r: str = recorded_robot) -> str:
        return f"gpmppi/{r}/{rel}"

    suppress: set[str] = set()
    for s in live:
        suppress |= {rkey(k) for k in rl.OUTPUTS[s.kind]} | {rkey(f"health/{s.name}")}
    start_s = req.start_s
    span = log_span_ns(parts)
    recorded_cmds: dict[int, tuple[float, float]] = {}
    if req.compare:
        for rec in iter_records(parts):
            if rec.key == rkey("cmd"):
                m = json.loads(rec.data)
                recorded_cmds[int(m["header"]["stamp_ns"])] = (float(m["v_ref"]), float(m["omega_ref"]))
        if not recorded_cmds:
            raise ReplaceError(f"--compare: the recording has no commands on {rkey('cmd')} to compare with")
        if start_s is None:
            # the recorded planner's first command answers one state: the live one starts from that state (and
            # the newest weights before it), so both plan the same states from the same start
            first_cmd = min(recorded_cmds)
            log_t0 = None
            for rec in iter_records(parts):
                log_t0 = rec.log_time_ns if log_t0 is None else log_t0
                if rec.key == rkey("state") and json.loads(rec.data)["header"]["stamp_ns"] == first_cmd:
                    start_s = max(0.0, (rec.log_time_ns - log_t0 - 1000) / 1e9)
                    _say(f"replay: comparing from the state of the recorded planner's first command, {start_s:.3f} s "
                         "into the log (give --start to choose)")
                    break
    options = PlayOptions(
        speed=req.speed, start_s=start_s, end_s=req.end_s, keys=req.keys, exclude=req.exclude, loop=req.loop,
        robot=req.robot, keep_stamps=req.keep_stamps, suppress=suppress,
        prime={rkey(k) for k in ("task", "terrain/weights", "estop")} if start_s else set(),
        track_key=rkey("state"),
        # compared: only the states the recorded planner answered (those it skipped, being busy, had no effect on it)
        only_stamps=set(recorded_cmds) if req.compare else None,
        lockstep_timeout_s=2.0 if req.lockstep else None,
    )
    launcher: Launcher | None = None
    session: zenoh.Session | None = None
    helper: zenoh.Session | None = None
    stop = stop or threading.Event()
    result: dict[str, Any] = {"services": [s.name for s in live]}
    try:
        if start_router or live or req.foxglove is not None:
            launch = LaunchFile(robot=robot)
            launch.router.listen = [endpoint]
            launcher = Launcher(launch, out=sys.stderr)
            if start_router:
                launcher.add("router", "router", {"listen": [endpoint]}, required=True)
            for s in live:
                launcher.add(s.name, s.kind, s.config, required=True)
                _say(f"replay: live {s.name} ({s.kind}) from the "
                     f"{'recorded settings' if s.from_metadata else 'defaults'}; its recorded outputs are not replayed")
            if req.foxglove is not None:  # served to Foxglove as it plays, like `gpmppi launch --foxglove`
                zenoh_cfg = {"mode": "client", "connect": [endpoint]}
                launcher.add("foxglove", "foxglove", {"robot": robot, "zenoh": zenoh_cfg, "host": req.foxglove[0],
                                                      "port": req.foxglove[1], "nice": 10}, required=False)
            launcher.start_all()
        else:
            try:
                wait_for_endpoint(endpoint, timeout_s=3.0)
            except TimeoutError:
                raise TimeoutError(f"no router at {endpoint}: start the stack (gpmppi launch), pass --connect "
                                   "ENDPOINT, or --port N to start a router for the replay") from None
        session = zenoh.open(copy_payloads(ZenohSettings(mode="client", connect=[endpoint]).to_config()))
        helper = zenoh.open(ZenohSettings(mode="client", connect=[endpoint]).to_config())
        live_cmds: list[tuple[int, float, float]] = []
        lock = threading.Condition()

        def on_cmd(sample: zenoh.Sample) -> None:
            try:
                m = json.loads(sample.payload.to_bytes())
                with lock:
                    live_cmds.append((int(m["header"]["stamp_ns"]), float(m["v_ref"]), float(m["omega_ref"])))
                    lock.notify_all()
            except (ValueError, KeyError, TypeError):
                pass

        def answered(stamp: int, timeout_s: float) -> bool:
            with lock:
                return lock.wait_for(lambda: any(c[0] == stamp for c in live_cmds[-8:]), timeout_s)

        subs = [session.declare_subscriber(f"gpmppi/{robot}/cmd", on_cmd)] if planners else []
        waiting = [*live, *([rl.LiveService("foxglove", "foxglove", {}, False)] if req.foxglove is not None else [])]
        if waiting:
            _wait_ready(session, robot, waiting, launcher, req.ready_timeout_s, stop)
        time.sleep(req.delay_s)  # subscriptions of listeners that just joined reach the router
        player = Player(session, lambda: iter_records(parts), options, stop=stop)
        player.declare(keys)
        player.answered = answered
        total_s = None if span is None else (span[1] - span[0]) / 1e9
        if req.end_s is not None:
            total_s = req.end_s if total_s is None else min(total_s, req.end_s)
        stats = _play_with_progress(player, total_s, req.progress)
        if not drain(session, helper):
            _say("replay: warning: the router did not confirm it took every message within 60 s; some may be lost")
        result["play"] = stats
        if live and not stop.is_set():
            time.sleep(req.settle_s)  # the live services' answers to the last inputs
        for sub in subs:
            sub.undeclare()
        if req.compare:
            with lock:
                got = list(live_cmds)
            result["compare"] = rl.compare(got, recorded_cmds, None if req.keep_stamps else player.stamp_map)
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
