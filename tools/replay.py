"""`gpmppi replay LOG.mcap`: a recording back onto Zenoh with its timing, optionally with live services in place
of recorded ones (`--replace planner`) and their commands compared with the recorded ones (`--compare`); or
converted offline for rerun (`--rerun save --rerun-target OUT.rrd | spawn | connect --rerun-target URL | serve`); or
served to Foxglove while it plays (`--foxglove HOST:PORT`); or copied with its Foxglove scene added, offline
(`--foxglove-scene OUT.mcap`)."""

from __future__ import annotations

import json
import math
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import typer

from tools.cli_checks import OUT_FILE, check_output_file, fail, only_with
from tools.replay_live import ReplaceError

RERUN_MODES = ("save", "spawn", "connect", "serve")


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


def _print(result: dict[str, Any], as_json: bool) -> None:
    stats = result["play"]
    if as_json:
        out: dict[str, Any] = dict(result.get("compare", {}))
        out = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in out.items()}
        out.update(published=stats.published, wall_s=round(stats.wall_s, 3), log_span_s=round(stats.log_span_s, 3),
                   lateness_ms=stats.lateness_summary(), suppressed=stats.suppressed, loops=stats.loops)
        typer.echo(json.dumps(out))
        return
    late = stats.lateness_summary()
    typer.echo(f"replayed {stats.published} messages on {len(stats.by_key)} keys: {stats.log_span_s:.2f} s of log "
               f"in {stats.wall_s:.2f} s" + (f" ({stats.loops} passes)" if stats.loops > 1 else ""))
    if late:
        typer.echo(f"timing: put after its due time by p50 {late['p50_ms']:.2f} ms, p99 {late['p99_ms']:.2f} ms, "
                   f"max {late['max_ms']:.2f} ms")
    skipped = ((stats.suppressed, "outputs of replaced services not replayed"),
               (stats.quarantined, "quarantined (_rejected) not replayed"),
               (stats.filtered, "filtered by --keys/--exclude"),
               (stats.unanswered, "states the recorded planner did not answer"),
               (stats.unshifted, "without a header, published unchanged"))
    extras = [f"{n} {what}" for n, what in skipped if n]
    if extras:
        typer.echo("skipped: " + "; ".join(extras))
    if "compare" in result:
        c = result["compare"]
        typer.echo(f"compare: {c['compared']} live commands matched with recorded ones (of {c['live_commands']} live), "
                   f"{c['exact']} of them bit for bit: "
                   f"v_ref RMS {c['v_rmse']:.4g} max {c['v_max']:.4g} m/s, omega_ref RMS {c['omega_rmse']:.4g} "
                   f"max {c['omega_max']:.4g} rad/s")
        if c.get("lockstep_misses") or c.get("lockstep_shifts"):
            typer.echo(f"lockstep: {c['lockstep_misses']} states not answered within 2 s, {c['lockstep_shifts']} "
                       "put so late that their stamps moved (their commands may differ)")


def register(app: typer.Typer) -> None:
    @app.command("replay")
    def replay(
        log: Path = typer.Argument(..., help="the MCAP recording (rotated parts _001, _002 ... follow)"),
        speed: float = typer.Option(
            1.0, min=0.0, help="playback speed (2: twice as fast; 0: as fast as Zenoh takes them)"
        ),
        start: float | None = typer.Option(None, min=0.0, help="begin this many seconds into the log"),
        end: float | None = typer.Option(None, min=0.0, help="stop this many seconds into the log"),
        keys: str | None = typer.Option(None, help="replay only keys matching this regular expression"),
        exclude: str | None = typer.Option(None, help="do not replay keys matching this regular expression"),
        loop: bool = typer.Option(False, help="start over at the end (until Ctrl-C)"),
        robot: str | None = typer.Option(None, help="publish under this robot name (gpmppi/NAME/...)"),
        keep_stamps: bool = typer.Option(False, help="keep the recorded header stamps (default: moved to now)"),
        replace: str | None = typer.Option(None, help="SERVICE[,SERVICE]: run these live, from the recorded "
                                           "settings, instead of replaying their outputs"),
        set_: list[str] = typer.Option([], "--set", help="SERVICE.FIELD=VALUE override of a replaced service"),
        config: list[str] = typer.Option([], "--config", help="SERVICE=FILE.yaml settings merged on the recorded"),
        compare: bool = typer.Option(False, help="compare the live planner's commands with the recorded ones"),
        as_json: bool = typer.Option(False, "--json", help="print one JSON object (compare results, timing)"),
        connect: str | None = typer.Option(None, help="router endpoint (default: tcp/127.0.0.1:7447; with "
                                           "--replace a router is started)"),
        port: int | None = typer.Option(
            None, min=1, max=65535, help="start a router on 127.0.0.1:PORT for the replay"
        ),
        delay: float = typer.Option(0.5, min=0.0, help="wait this long after joining before the first message [s]"),
        ready_timeout: float = typer.Option(
            600.0, min=0.1, help="wait this long for live services to come up [s]"
        ),
        rerun: str | None = typer.Option(None, help="convert offline for rerun (no Zenoh): save | spawn | connect | "
                                         "serve"),
        rerun_target: str | None = typer.Option(
            None, "--rerun-target", help="with --rerun save: the .rrd file to write; with --rerun connect: the URL"
        ),
        foxglove: str | None = typer.Option(
            None, "--foxglove", metavar="HOST:PORT",
            help="serve the replay to Foxglove on this WebSocket address (HOST:PORT or PORT; loopback by default)",
        ),
        foxglove_scene: Path | None = typer.Option(
            None, "--foxglove-scene", metavar=OUT_FILE,
            help="offline, no Zenoh: write the recording with its Foxglove 3D scene added to this new MCAP file",
        ),
        profile: Path | None = typer.Option(
            None, help="with --replace: the robot profile (`gpmppi train`) the replaced planner and terrain services "
            "run with (default: the one the recording attached)"),
        quiet: bool = typer.Option(False, help="no progress bar"),
        lockstep: bool = typer.Option(False, help="with --compare: put each state only after the live planner "
                                      "answered the one before (for a live planner slower than the recorded one)"),
    ) -> None:
        """Replay a recording onto Zenoh (like `ros2 bag play`), with live services in place of recorded ones
        (`--replace`, like `dora replay --replace`), or convert it for rerun (`--rerun`)."""
        from services.recording.player_log import LogError
        from tools.service_cmd import foxglove_address

        if start is not None and end is not None and end <= start:
            fail(f"--end {end}: must be after --start {start}")
        if foxglove_scene is not None:
            given = [name for name, on in {"--rerun": rerun is not None, "--foxglove": foxglove is not None,
                                           "--replace": replace is not None, "--compare": compare, "--loop": loop,
                                           "--start": start is not None, "--end": end is not None,
                                           "--keys": keys is not None, "--exclude": exclude is not None}.items() if on]
            if given:
                fail(f"{', '.join(given)}: not with --foxglove-scene (an offline copy of the whole recording)")
            from services.recording.player_log import LogError, check_log
            from services.view.foxglove_log import add_scene

            try:
                check_log(log)
            except LogError as exc:
                fail(str(exc))
            stats = add_scene(log, foxglove_scene)
            typer.echo(json.dumps(stats) if as_json else
                       f"wrote {foxglove_scene}: {stats['messages']} messages and {stats['scene_messages']} scene "
                       f"messages in {stats['wall_s']:.2f} s (open it in Foxglove)")
            return
        address = foxglove_address(foxglove)
        if rerun is not None and address is not None:
            fail("--foxglove serves a replay onto Zenoh; --rerun converts offline: give one")
        if rerun is not None:
            live_only = {"--speed": speed != 1.0, "--loop": loop, "--robot": robot is not None,
                         "--keep-stamps": keep_stamps, "--replace": replace is not None, "--set": bool(set_),
                         "--config": bool(config), "--compare": compare, "--connect": connect is not None,
                         "--port": port is not None, "--delay": delay != 0.5, "--ready-timeout": ready_timeout != 600.0,
                         "--lockstep": lockstep}
            given = [name for name, on in live_only.items() if on]
            if given:
                fail(f"{', '.join(given)}: only for a replay onto Zenoh, not with --rerun (an offline conversion)")
            if rerun == "save" and rerun_target is not None:
                check_output_file("--rerun-target", Path(rerun_target))
        try:
            if rerun is not None:
                if rerun not in RERUN_MODES:
                    raise ValueError(f"--rerun {rerun!r}: expected one of {', '.join(RERUN_MODES)}")
                if rerun in ("save", "connect") and rerun_target is None:
                    raise ValueError(f"--rerun {rerun} needs --rerun-target (save: OUT.rrd; connect: URL)")
                try:
                    from tools.replay_rerun import convert
                except ImportError as exc:
                    raise RuntimeError(f"--rerun: the offline rerun conversion is not available in this build ({exc})"
                                       ) from None

                stats = convert(log, rerun, rerun_target, start_s=start, end_s=end, keys=keys, exclude=exclude)
                typer.echo(json.dumps(stats) if as_json else
                           f"converted {stats.get('messages')} messages ({stats.get('log_duration_s', 0):.1f} s of "
                           f"log) in {stats.get('wall_s', 0):.2f} s")
                return
            if rerun_target is not None:
                raise ValueError(f"--rerun-target {rerun_target!r}: only with --rerun save or --rerun connect")
            only_with(replace is not None, "--replace SERVICE", {
                "--set": bool(set_), "--config": bool(config), "--compare": compare, "--profile": profile is not None})
            only_with(compare, "--compare", {"--lockstep": lockstep})
            if port is not None and connect is not None:
                raise ValueError("give --connect ENDPOINT (an existing router) or --port N (start one), not both")
            req = ReplayRequest(log, speed, start, end, keys, exclude, loop, robot, keep_stamps, replace, list(set_),
                                list(config), compare, connect, port, delay, ready_timeout,
                                progress=not (quiet or as_json), lockstep=lockstep, foxglove=address, profile=profile)
            stop = threading.Event()
            from services.runtime.signals import StopSignals

            with StopSignals(lambda signum: stop.set(), [signal.SIGINT]):
                result = run_replay(req, stop)
        except (LogError, ReplaceError, ValueError, FileNotFoundError, TimeoutError, RuntimeError) as exc:
            typer.echo(f"gpmppi replay: {exc}", err=True)
            raise typer.Exit(2) from None
        _print(result, as_json)
