"""The launcher (supervisor): `gpmppi launch [LAUNCH.yaml] [--duration S] [--record FILE.mcap]
[--rerun spawn|save FILE|connect URL|off] [--port N]`.

Starts the Zenoh router and each service as its own process (`python -m services.run NAME --config FILE`),
prefixes their logs, restarts a crashed service with backoff, stops all in reverse order on Ctrl-C
(SIGINT, then SIGTERM, then SIGKILL after timeouts) and prints a summary. Exit status 1 when a required
service failed for good.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from services.monitor import Monitor, Summary, summarize
from services.node import ZenohSettings
from services.run import SERVICES

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_LAUNCH = Path(__file__).resolve().parent / "launch" / "default.yaml"


class RouterEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(True, description="start a router process (False: use an existing router or peers)")
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"], description="router endpoints")
    config: dict[str, Any] = Field(default_factory=dict, description="extra router settings")


class ServiceEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(description="unique name of this process (service name in keys and logs)")
    kind: str | None = Field(None, description="which service to run (default: the name)")
    required: bool = Field(True, description="the launch fails when this service fails for good")
    enabled: bool = Field(True, description="start it at all")
    config: dict[str, Any] = Field(default_factory=dict, description="the service's settings")


class LaunchFile(BaseModel):
    model_config = ConfigDict(extra="forbid")
    robot: str = Field("jackal", description="robot name in every key")
    router: RouterEntry = Field(default_factory=RouterEntry)
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings, description="how services join")
    services: list[ServiceEntry] = Field(default_factory=list)
    max_restarts: int = Field(3, ge=0, description="restarts of a crashed service before it has failed for good")
    restart_backoff_s: float = Field(0.5, gt=0, description="first restart delay; doubles each time (max 8 s)")
    stop_timeout_s: float = Field(5.0, gt=0, description="wait after SIGINT, then after SIGTERM, before escalating")

    @classmethod
    def load(cls, path: str | Path) -> LaunchFile:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"launch file {path} does not exist")
        try:
            return cls.model_validate(yaml.safe_load(path.read_text()) or {})
        except ValidationError as exc:
            raise ValueError(f"launch file {path}: {exc}") from exc


@dataclass
class Child:
    name: str
    kind: str
    config_path: Path
    required: bool
    process: subprocess.Popen | None = None
    restarts: int = 0
    failed: bool = False
    restart_at: float | None = None
    started_at: float = 0.0
    first_started_at: float = 0.0
    exit_codes: list[int] = field(default_factory=list)


class Launcher:
    def __init__(self, launch: LaunchFile, out: IO[str] = sys.stdout) -> None:
        self.launch = launch
        self.out = out
        self.children: list[Child] = []
        self.stop_event = threading.Event()
        self._print_lock = threading.Lock()
        # held while a child's process is replaced (supervise, restart, stop_all): supervise must not take a
        # deliberate stop for a crash
        self._process_lock = threading.RLock()
        self.run_dir = Path(tempfile.mkdtemp(prefix="gpmppi-launch-"))
        self.t0 = time.monotonic()

    # ---- output -------------------------------------------------------------------------------
    def say(self, name: str, line: str) -> None:
        with self._print_lock:
            self.out.write(f"[{name:>9}] {line.rstrip()}\n")
            self.out.flush()

    def _pump(self, child: Child, stream: IO[bytes]) -> None:
        for raw in iter(stream.readline, b""):
            self.say(child.name, readable(raw.decode(errors="replace")))
        stream.close()

    # ---- processes ----------------------------------------------------------------------------
    def _write_config(self, name: str, config: dict[str, Any]) -> Path:
        path = self.run_dir / f"{name}.yaml"
        path.write_text(yaml.safe_dump(config, sort_keys=False))
        return path

    def add(self, name: str, kind: str, config: dict[str, Any], required: bool) -> None:
        if kind not in SERVICES:
            raise ValueError(f"service {name!r}: unknown kind {kind!r}; known: {', '.join(SERVICES)}")
        if any(c.name == name for c in self.children):
            raise ValueError(f"two services are named {name!r}; names must be unique")
        self.children.append(Child(name, kind, self._write_config(name, config), required))

    def _spawn(self, child: Child) -> None:
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
        env["PYTHONUNBUFFERED"] = "1"
        child.process = subprocess.Popen(
            [sys.executable, "-m", "services.run", child.kind, "--config", str(child.config_path)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env=env,
            cwd=os.getcwd(),
            start_new_session=True,  # Ctrl-C reaches only the launcher, which stops children in order
        )
        child.started_at = time.monotonic()
        child.first_started_at = child.first_started_at or child.started_at
        assert child.process.stdout is not None
        threading.Thread(target=self._pump, args=(child, child.process.stdout), daemon=True).start()
        self.say("launch", f"started {child.name} ({child.kind}) pid {child.process.pid}")

    def start_all(self) -> None:
        for child in self.children:
            self._spawn(child)
            if child.kind == "router":
                wait_for_endpoint(self.launch.router.listen[0], timeout_s=10.0)

    def supervise(self) -> None:
        """Restart crashed services with backoff; mark them failed after max_restarts."""
        with self._process_lock:
            self._supervise(time.monotonic())

    def _supervise(self, now: float) -> None:
        for child in self.children:
            if child.failed or child.process is None:
                continue
            code = child.process.poll()
            if child.restart_at is not None:
                if now >= child.restart_at:
                    child.restart_at = None
                    child.restarts += 1
                    self._spawn(child)
                continue
            if code is None:
                continue
            child.exit_codes.append(code)
            if child.restarts >= self.launch.max_restarts:
                child.failed = True
                self.say("launch", f"{child.name} exited with {code} and has failed for good")
                if child.required:
                    self.stop_event.set()
                continue
            delay = min(8.0, self.launch.restart_backoff_s * 2**child.restarts)
            child.restart_at = now + delay
            self.say("launch", f"{child.name} exited with {code}; restart {child.restarts + 1} in {delay:.1f} s")

    def stop_all(self) -> None:
        """Reverse start order: SIGINT, wait, SIGTERM, wait, SIGKILL."""
        with self._process_lock:
            for child in reversed(self.children):
                self._stop(child)

    def _stop(self, child: Child) -> None:
        timeout = self.launch.stop_timeout_s
        p = child.process
        if p is None or p.poll() is not None:
            return
        for sig, wait_s in ((signal.SIGINT, timeout), (signal.SIGTERM, timeout), (signal.SIGKILL, timeout)):
            try:
                p.send_signal(sig)
            except ProcessLookupError:
                break
            try:
                p.wait(wait_s)
                break
            except subprocess.TimeoutExpired:
                self.say("launch", f"{child.name} ignored {sig.name} for {wait_s:.0f} s")
        self.say("launch", f"stopped {child.name} (exit {p.returncode})")

    def restart(self, name: str) -> Child:
        """Stop a running service as stop_all does and start it again at once (a deliberate restart, e.g. to
        measure its start-up; not counted in `restarts`). The child's `started_at` is the new process's start."""
        with self._process_lock:
            child = next((c for c in self.children if c.name == name), None)
            if child is None:
                raise KeyError(f"no service named {name!r}; running: {', '.join(c.name for c in self.children)}")
            if child.failed or child.restart_at is not None:
                raise RuntimeError(f"{name} is not running (failed or waiting for a crash restart)")
            self._stop(child)
            self._spawn(child)
            return child

    def failed_required(self) -> list[str]:
        return [c.name for c in self.children if c.failed and c.required]


def readable(line: str) -> str:
    """A service's JSON log line as `LEVEL message key=value ...` (other lines unchanged)."""
    try:
        entry = json.loads(line)
    except ValueError:
        return line
    if not isinstance(entry, dict) or "msg" not in entry:
        return line
    skip = {"t", "level", "service", "logger", "msg"}
    extras = " ".join(f"{k}={v}" for k, v in entry.items() if k not in skip and k != "exc")
    text = f"{entry.get('level', ''):<7} {entry['msg']} {extras}".rstrip()
    return text + ("\n" + entry["exc"] if "exc" in entry else "")


def wait_for_endpoint(endpoint: str, timeout_s: float) -> None:
    """Wait until a tcp/<host>:<port> endpoint accepts connections."""
    import socket

    if not endpoint.startswith("tcp/"):
        time.sleep(0.5)
        return
    host, port = endpoint[4:].rsplit(":", 1)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.create_connection((host, int(port)), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"the router did not open {endpoint} within {timeout_s} s")


def build(
    launch: LaunchFile,
    record: str | None,
    rerun: list[str] | None,
    port: int | None,
    launch_path: str | Path | None = None,
) -> tuple[Launcher, list[str]]:
    if port is not None:
        endpoint = f"tcp/127.0.0.1:{port}"
        launch.router.listen = [endpoint]
        launch.zenoh.connect = [endpoint]
    launcher = Launcher(launch)
    common = {"robot": launch.robot, "zenoh": launch.zenoh.model_dump()}
    if launch.router.enabled:
        launcher.add("router", "router", {"listen": launch.router.listen, **launch.router.config}, required=True)
    entries = [e for e in launch.services if e.enabled]
    names = [e.name for e in entries]
    if record:
        # recorder and viewer start first so they see the others' first messages; both at a lower CPU priority
        # (nice) than the control path, which they must never delay
        entries.insert(0, ServiceEntry(name="recorder", required=False, config={"path": record, "nice": 10}))
    if rerun and rerun[0] != "off":
        mode = rerun[0]
        config: dict[str, Any] = {"mode": mode, "nice": 10}
        if mode == "save":
            config["path"] = rerun[1] if len(rerun) > 1 else "runs/view.rrd"
        elif mode == "connect" and len(rerun) > 1:
            config["url"] = rerun[1]
        entries.insert(0, ServiceEntry(name="viewer", required=False, config=config))
    entries = _describe_run_to_recorders(launcher, entries, launch_path)
    for e in entries:
        launcher.add(e.name, e.kind or e.name, {**common, **e.config, "service": e.name}, e.required)
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


def run_launch(
    launch_path: str | Path | None = None,
    duration: float | None = None,
    record: str | None = None,
    rerun: list[str] | None = None,
    port: int | None = None,
    out: IO[str] | None = None,
    ready_timeout_s: float = 600.0,
    then: Callable[[Launcher, Monitor], None] | None = None,
) -> tuple[int, Summary]:
    """Run a launch file (default: the simulated Jackal) for `duration` seconds after every service is up
    (first heartbeat; a cold numba cache can take minutes), or until Ctrl-C; (exit code, summary).

    `then`, if given, runs in a thread once every service is up, instead of the `duration`; the run ends when
    it returns (it should return soon after `launcher.stop_event` is set). Its exception is raised here."""
    launch = LaunchFile.load(launch_path or DEFAULT_LAUNCH)
    launcher, service_names = build(launch, record, rerun, port, launch_path or DEFAULT_LAUNCH)
    launcher.out = out or sys.stdout
    interrupted = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        interrupted.set()
        launcher.stop_event.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
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
    try:
        launcher.start_all()
        monitor = Monitor(launch.robot, launch.zenoh, t_start)
        expected = {c.name for c in launcher.children if c.kind != "router"}
        ready_by = time.monotonic() + ready_timeout_s
        deadline: float | None = None
        while not launcher.stop_event.is_set():
            launcher.supervise()
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
            launcher.stop_event.wait(0.1)
    finally:
        launcher.stop_event.set()
        if hook is not None:
            hook.join(launcher.launch.stop_timeout_s * 3 + 5.0)
        launcher.stop_all()
        if monitor is not None:
            monitor.close()
        for s, handler in previous.items():
            signal.signal(s, handler)
    summary = summarize(monitor, launcher, service_names, record)
    for line in summary.lines():
        launcher.say("summary", line)
    if hook_errors:
        raise hook_errors[0]
    failed = launcher.failed_required()
    return (1 if failed else 0), summary


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="gpmppi launch", description="Run a gpmppi launch file.")
    parser.add_argument("launch_file", nargs="?", default=None, help="launch YAML (default: simulated Jackal)")
    parser.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    parser.add_argument("--record", default=None, help="record everything to this MCAP file")
    parser.add_argument(
        "--rerun", nargs="+", default=None, metavar="MODE", help="spawn | save FILE.rrd | connect URL | off"
    )
    parser.add_argument("--port", type=int, default=None, help="router port on 127.0.0.1 (overrides the file)")
    args = parser.parse_args(argv)
    if args.rerun and (args.rerun[0] not in ("spawn", "save", "connect", "off") or len(args.rerun) > 2):
        parser.error(f"--rerun takes spawn | save FILE | connect URL | off, got {' '.join(args.rerun)}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        code, _ = run_launch(args.launch_file, args.duration, args.record, args.rerun, args.port)
    except (FileNotFoundError, ValueError, TimeoutError) as exc:
        print(f"gpmppi launch: {exc}", file=sys.stderr)
        return 2
    return code


if __name__ == "__main__":
    sys.exit(main())
