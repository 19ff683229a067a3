"""`gpmppi replay LOG.mcap`: a recording back onto Zenoh with its timing, optionally with live services in place
of recorded ones (`--replace planner`) and their commands compared with the recorded ones (`--compare`); or
converted offline for rerun (`--rerun save --rerun-target OUT.rrd | spawn | connect --rerun-target URL | serve`); or
served to Foxglove while it plays (`--foxglove HOST:PORT`); or copied with its Foxglove scene added, offline
(`--foxglove-scene OUT.mcap`)."""

from __future__ import annotations

import json
import math
import signal
import threading
from pathlib import Path
from typing import Any

import typer

from tools.cli_checks import OUT_FILE, check_output_file, fail, only_with
from tools.replay_live import ReplaceError
from tools.replay_run import ReplayRequest, run_replay

RERUN_MODES = ("save", "spawn", "connect", "serve")


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
