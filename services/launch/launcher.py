"""The launcher (supervisor): `gpmppi launch [LAUNCH.yaml] [--duration S] [--record FILE.mcap]
[--rerun spawn|save FILE|connect URL|serve|off] [--port N] [--secrets DIR] [--foxglove HOST:PORT]`.

Starts the Zenoh router and each service as its own process (`python -m services.run NAME --config FILE`),
prefixes their logs, restarts a crashed service with backoff (a thread waits on each process, so a death is
seen at once), stops all in reverse order on Ctrl-C (SIGINT, then SIGTERM, then SIGKILL after timeouts) and
prints a summary with every restart and its cause. Exit status 1 when a required service failed for good;
2 when the launch cannot start (bad launch file, no router to connect to).
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import zenoh

from services.launch.launch_file import (
    DEFAULT_LAUNCH,
    LaunchFile,
    LaunchFileError,
    ServiceEntry,
    check_profile_grounds,
    load_launch,
    profile_configs,
)
from services.launch.monitor import Monitor, Summary, summarize
from services.launch.supervisor import Launcher
from services.recording.output_files import resolve_output
from services.runtime.config_file import Marks, locate, one_line, validation_problems
from services.runtime.node_settings import ZenohSettings
from services.runtime.session import StoppedWhileWaiting
from services.runtime.signals import StopSignals
from services.security.secure_check import check_launch_secrets

# services that join a secured stack as another identity: the Foxglove server reads everything, as the viewer does
VIEWER_IDENTITIES = {"foxglove": "viewer"}


class RouterUnreachable(RuntimeError):
    """The launch file starts no router and none answers at its endpoint."""


def build(
    launch: LaunchFile,
    record: str | None,
    rerun: list[str] | None,
    port: int | None,
    secrets: str | None = None,
    launch_path: str | Path | None = None,
    foxglove: tuple[str, int] | None = None,
) -> tuple[Launcher, list[str]]:
    if port is not None:
        endpoint = f"tcp/127.0.0.1:{port}"
        launch.router.listen = [endpoint]
        launch.zenoh.connect = [endpoint]
    # --secrets: checked before anything starts; each session joins as its own identity (services/security/secure.py)
    secured = None
    if secrets is not None:
        secured = check_launch_secrets(launch, secrets, record, rerun, foxglove is not None)
    launcher = Launcher(launch)
    common = {"robot": launch.robot, "zenoh": launch.zenoh.model_dump()}
    if launch.router.enabled:
        router = {"listen": launch.router.listen, **launch.router.config}
        if secured is not None:
            router["router_config_file"] = str(secured.router_file)
        launcher.add("router", "router", router, required=True)
    entries = [e for e in launch.services if e.enabled]
    names = [e.name for e in entries]
    if record:
        # recorder and viewer start first so they see the others' first messages; both at a lower CPU priority
        # (nice) than the control path, which they must never delay
        # with --foxglove the recording carries the Foxglove scene too, so it opens in Foxglove as the run looked live
        config = {"path": record, "nice": 10, **({"foxglove_scene": True} if foxglove is not None else {})}
        entries.insert(0, ServiceEntry(name="recorder", required=False, config=config))
    if rerun and rerun[0] != "off":
        mode = rerun[0]
        config: dict[str, Any] = {"mode": mode, "nice": 10}
        if mode == "save":
            config["path"] = rerun[1] if len(rerun) > 1 else "runs/view.rrd"
        elif mode == "connect" and len(rerun) > 1:
            config["url"] = rerun[1]
        entries.insert(0, ServiceEntry(name="viewer", required=False, config=config))
    if foxglove is not None:
        # the Foxglove server: a viewer like rerun's, at the same lower priority, never required
        config = {"host": foxglove[0], "port": foxglove[1], "nice": 10}
        entries.insert(0, ServiceEntry(name="foxglove", required=False, config=config))
    entries = _describe_run_to_recorders(launcher, profile_configs(launch, entries), launch_path)
    for e in entries:
        config = {**common, **e.config, "service": e.name}
        if secured is not None:
            identity = VIEWER_IDENTITIES.get(e.kind or e.name, e.kind or e.name)
            config["zenoh"] = {**config["zenoh"], "config_file": str(secured.client_file(identity))}
        launcher.add(e.name, e.kind or e.name, config, e.required)
    if secured is not None:
        launch.zenoh.config_file = str(secured.client_file("launcher"))  # the launcher's own Monitor session
    return launcher, names


def _describe_run_to_recorders(
    launcher: Launcher, entries: list[ServiceEntry], launch_path: str | Path | None
) -> list[ServiceEntry]:
    """Tell each recorder where every service's settings file will be (the launcher writes each to
    run_dir/<name>.yaml) and which launch file ran, so it records their resolved settings and attaches the
    launch file. Settings given in the launch file win."""
    configs = {c.name: {"kind": c.kind, "config": str(c.config_path)} for c in launcher.children}
    for e in entries:
        configs[e.name] = {"kind": e.kind or e.name, "config": str(launcher.run_dir / f"{e.name}.yaml")}
    run = {"service_configs": configs, "launch_file": str(Path(launch_path).resolve()) if launch_path else None}
    return [
        e.model_copy(update={"config": {**run, **e.config}}) if (e.kind or e.name) == "recorder" else e
        for e in entries
    ]


def check_launch(
    launch: LaunchFile, path: str | Path, marks: Marks | None = None, extra: list[ServiceEntry] | None = None
) -> None:
    """Every enabled service's settings, as the launcher will write them (the launch file's robot and zenoh under
    the entry's own config), and the router's, validated before anything starts: `LaunchFileError`, one line with
    each problem at its line in the user's file (`FILE:LINE:COL: services[2] (planner).config.horizon: ...`),
    instead of one service's exit at its start, retried, naming a temporary copy. `extra`: services the command
    line adds (recorder, viewer), which have no place in the file."""
    from pydantic import ValidationError

    from services.run import SERVICES, settings_class

    marks = marks or {}
    problems: list[str] = []
    common = {"robot": launch.robot, "zenoh": launch.zenoh.model_dump()}
    if launch.router.enabled:
        try:
            settings_class("router").model_validate({"listen": launch.router.listen, **launch.router.config})
        except ValidationError as exc:
            problems += validation_problems(exc, path, marks, ("router", "config"), "router.config")
    entries = [(i, e) for i, e in enumerate(profile_configs(launch, launch.services))] + [
        (None, e) for e in extra or []]
    for i, entry in entries:
        kind = entry.kind or entry.name
        label = f"services[{i}] ({entry.name})" if i is not None else f"{entry.name} (from the command line)"
        if not entry.enabled:
            continue
        if kind not in SERVICES:
            where = locate(marks, ("services", i, "kind" if entry.kind else "name")) if i is not None else None
            at = f"{path}:{where[0]}:{where[1]}" if where else str(path)
            problems.append(f"{at}: {label}: unknown service kind {kind!r}; known: {', '.join(SERVICES)}")
            continue
        try:
            settings_class(kind).model_validate({**common, **entry.config, "service": entry.name})
        except ValidationError as exc:
            for err in exc.errors():
                # robot and zenoh come from the top of the file unless the entry sets its own
                top = bool(err["loc"]) and err["loc"][0] in common and err["loc"][0] not in entry.config
                prefix: tuple = () if top or i is None else ("services", i, "config")
                one = ValidationError.from_exception_data(exc.title, [err])  # type: ignore[list-item]
                problems += validation_problems(one, path, marks, prefix, "" if top else f"{label}.config")
    if problems:
        raise LaunchFileError(f"{one_line(problems)}; fix it in the launch file")


def check_run(duration: float | None, port: int | None) -> None:
    """The command line's numbers, before anything starts: ValueError naming the setting."""
    if duration is not None and not (math.isfinite(duration) and duration > 0):
        raise ValueError(
            f"duration must be a positive number of seconds, got {duration}; leave it out to run until Ctrl-C"
        )
    if port is not None and not (isinstance(port, int) and 1 <= port <= 65535):
        raise ValueError(f"port must be a TCP port number in 1..65535, got {port}")


def resolve_outputs(
    record: str | None, rerun: list[str] | None
) -> tuple[str | None, list[str] | None, list[str]]:
    """(the recording's file, the rerun options with the .rrd file, notes): `--record` and `--rerun save` as the
    files that will be written (services.recording.output_files.resolve_output: never an existing file, a folder gets a
    file inside it, a missing folder is an error), decided before anything starts."""
    notes: list[str] = []
    if record:
        path, note = resolve_output(record, ".mcap")
        record = str(path)
        notes += [f"recording: {note}"] if note else []
    if rerun and rerun[0] == "save":
        given = rerun[1] if len(rerun) > 1 else None
        if given is None:  # the default file, in a folder of our own
            Path("runs").mkdir(exist_ok=True)
        path, note = resolve_output(given or "runs/view.rrd", ".rrd")
        if record and str(path) == record:
            raise ValueError(f"--record and --rerun save name the same file {path}; give two files")
        rerun = ["save", str(path)]
        notes += [f"rerun: {note}"] if note else []
    return record, rerun, notes


def run_launch(
    launch_path: str | Path | None = None,
    duration: float | None = None,
    record: str | None = None,
    rerun: list[str] | None = None,
    port: int | None = None,
    out: IO[str] | None = None,
    ready_timeout_s: float = 600.0,
    then: Callable[[Launcher, Monitor], None] | None = None,
    secrets: str | None = None,
    foxglove: tuple[str, int] | None = None,
    edit: Callable[[LaunchFile], LaunchFile] | None = None,
) -> tuple[int, Summary]:
    """Run a launch file (default: the simulated Jackal) for `duration` seconds after every service is up
    (first heartbeat; a cold numba cache can take minutes), or until Ctrl-C; (exit code, summary).

    `then`, if given, runs in a thread once every service is up, instead of the `duration`; the run ends when
    it returns (it should return soon after `launcher.stop_event` is set; the services are stopped after it
    returns, so it may still talk to them then). Its exception is raised here.

    `edit`, if given, changes the loaded launch file before it is checked (a command that runs a launch file with a
    service of its own in place of one of the file's, as `gpmppi calibrate drive` does)."""
    # everything that can be checked is checked before any process starts (or any file is written)
    check_run(duration, port)
    path = launch_path or DEFAULT_LAUNCH
    launch, marks = load_launch(path)
    if edit is not None:
        launch = edit(launch)
    check_launch(launch, path, marks)
    ground_notes = check_profile_grounds(launch, path)
    record, rerun, notes = resolve_outputs(record, rerun)
    notes = ground_notes + notes
    launcher, service_names = build(launch, record, rerun, port, secrets, path, foxglove)
    launcher.out = out or sys.stdout
    for note in notes:
        launcher.say("launch", note)
    interrupted = threading.Event()

    def on_signal(signum: int) -> None:
        interrupted.set()
        launcher.request_stop()

    stop_signals = StopSignals(on_signal)
    monitor: Monitor | None = None
    hook: threading.Thread | None = None
    hook_errors: list[BaseException] = []

    def run_hook(launcher: Launcher, monitor: Monitor) -> None:
        assert then is not None
        try:
            then(launcher, monitor)
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
            hook_errors.append(exc)

    t_start = time.monotonic()
    outside_router = not launch.router.enabled and launch.zenoh.mode == "client"
    # the launcher's own session: at once for a router it starts; an outside router must be up now (wait_s 0),
    # or may come up while the services, started first, wait for it themselves
    wait_s = launch.router.wait_s if outside_router else 10.0
    monitor_zenoh = launch.zenoh.model_copy(update={"wait_for_router_s": wait_s})
    try:
        if outside_router and wait_s == 0:
            monitor = open_monitor(launch, monitor_zenoh, t_start, launch_path)
        launcher.start_all()
        if monitor is None:
            if outside_router:
                endpoints = ", ".join(launch.zenoh.connect)
                launcher.say("launch", f"waiting up to {wait_s:.0f} s for the router at {endpoints}")
            monitor = open_monitor(launch, monitor_zenoh, t_start, launch_path, launcher.stop_event)
        launcher.last_payload = monitor.last_payload  # what a service's next process resumes from
        expected = {c.name for c in launcher.children if c.kind != "router"}
        ready_by = time.monotonic() + ready_timeout_s
        deadline: float | None = None
        while not launcher.stop_event.is_set():
            launcher.wake.clear()  # before supervise: a death from here on ends the wait below at once
            wait = launcher.supervise()
            now = time.monotonic()
            if deadline is None and hook is None and (duration is not None or then is not None):
                with monitor.lock:
                    seen = set(monitor.heartbeats)
                up = expected - {c.name for c in launcher.children if c.failed} <= seen
                if up or now >= ready_by:
                    state = "all services up" if up else f"not all services up after {ready_timeout_s:.0f} s"
                    if then is not None:
                        launcher.say("launch", f"{state} ({now - t_start:.1f} s); running {then.__name__}")
                        hook = threading.Thread(target=run_hook, args=(launcher, monitor), daemon=True)
                        hook.start()
                    else:
                        assert duration is not None
                        launcher.say("launch", f"{state} ({now - t_start:.1f} s); running {duration:.0f} s")
                        deadline = now + duration
            if deadline is not None and now >= deadline:
                break
            if hook is not None and not hook.is_alive():
                break
            # a child's death wakes this wait at once (its watcher thread); restarts due sooner shorten it
            launcher.wake.wait(wait)
    finally:
        launcher.stop_event.set()
        if hook is not None:
            hook.join(launcher.launch.stop_timeout_s * 3 + 5.0)
        launcher.stop_all()
        if monitor is not None:
            monitor.close()
        stop_signals.restore()
    summary = summarize(monitor, launcher, service_names, record)
    summary.rerun_file = rerun[1] if rerun and rerun[0] == "save" else None
    summary.notes = notes
    for line in summary.lines():
        launcher.say("summary", line)
    if hook_errors:
        raise hook_errors[0]
    failed = launcher.failed_required()
    return (1 if failed else 0), summary


def open_monitor(
    launch: LaunchFile, zenoh_settings: ZenohSettings, t_start: float, path: str | Path | None,
    stop: threading.Event | None = None,
) -> Monitor:
    """The launcher's session; an unreachable router is one line naming the endpoint and what to start."""
    endpoints = ", ".join(launch.zenoh.connect)
    try:
        return Monitor(launch.robot, zenoh_settings, t_start, stop)
    except StoppedWhileWaiting:
        raise RouterUnreachable(f"stopped while waiting for the router at {endpoints}") from None
    except zenoh.ZError as exc:
        if launch.router.enabled:
            raise RouterUnreachable(f"cannot join the router this launch started at {endpoints}: {exc}") from None
        waited = f" within {launch.router.wait_s:.0f} s" if launch.router.wait_s else ""
        raise RouterUnreachable(
            f"no Zenoh router at {endpoints}{waited}, and {path or DEFAULT_LAUNCH} starts none (router.enabled: "
            "false): start it first (on the robot `ros2 run rmw_zenoh_cpp rmw_zenohd`, or `gpmppi service router`), "
            "or set router.enabled: true, or router.wait_s to wait for it"
        ) from None


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="gpmppi launch", description="Run a gpmppi launch file.")
    parser.add_argument("launch_file", nargs="?", default=None, help="launch YAML (default: simulated Jackal)")
    parser.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    parser.add_argument("--record", default=None, help="record everything to this MCAP file")
    parser.add_argument(
        "--rerun", nargs="+", default=None, metavar="MODE", help="spawn | save FILE.rrd | connect URL | off"
    )
    parser.add_argument("--port", type=int, default=None, help="router port on 127.0.0.1 (overrides the file)")
    parser.add_argument(
        "--secrets", default=None, metavar="DIR", help="run secured with the identities of `gpmppi secure init DIR`"
    )
    parser.add_argument(
        "--foxglove", default=None, metavar="HOST:PORT", help="serve the run to Foxglove on this WebSocket address"
    )
    args = parser.parse_args(argv)
    if args.foxglove is not None:
        host, _, port = args.foxglove.rpartition(":")
        if not port.isdigit() or not 1 <= int(port) <= 65535:
            parser.error(f"--foxglove takes HOST:PORT or PORT, got {args.foxglove}")
        args.foxglove = (host.strip("[]") or "127.0.0.1", int(port))
    if args.rerun and (args.rerun[0] not in ("spawn", "save", "connect", "serve", "off") or len(args.rerun) > 2):
        parser.error(f"--rerun takes spawn | save FILE | connect URL | serve | off, got {' '.join(args.rerun)}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        code, _ = run_launch(
            args.launch_file, args.duration, args.record, args.rerun, args.port, secrets=args.secrets,
            foxglove=args.foxglove,
        )
    except (FileNotFoundError, ValueError, TimeoutError, RouterUnreachable) as exc:
        print(f"gpmppi launch: {exc}", file=sys.stderr)
        return 2
    return code


if __name__ == "__main__":
    sys.exit(main())
