"""The launcher's supervision: each service a child process, its output prefixed, its death seen at once (a
thread waits on each process) and answered with a restart after a backoff; a stop in reverse order.
`services.launch.launcher` builds a `Launcher` from a launch file and runs it."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import yaml

from services.recording.output_files import free_name
from services.run import LAUNCHER_PID_ENV, SERVICES

if TYPE_CHECKING:
    from services.launch.launch_file import LaunchFile

REPO_ROOT = Path(__file__).resolve().parents[2]


class _Spawner:
    """One thread, alive as long as this process, that starts every child process of every launcher.

    Each child asks the kernel for SIGTERM when its parent dies (PR_SET_PDEATHSIG, `services.run.follow_launcher`),
    and Linux takes the *thread* that forked the child for its parent: a child started from a thread that then
    ends (a `then` hook calling `Launcher.restart`, a test's helper thread) would be sent SIGTERM at that moment.
    So no thread but this one, which ends only with the process, forks a child."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._requests: queue.SimpleQueue[tuple[tuple[Any, ...], dict[str, Any], dict[str, Any], threading.Event]] = (
            queue.SimpleQueue()
        )
        self._thread: threading.Thread | None = None

    def popen(self, *args: Any, **kwargs: Any) -> subprocess.Popen:
        """`subprocess.Popen(*args, **kwargs)`, run on the spawner thread; its exception is raised here."""
        with self._lock:
            if self._thread is None:
                self._thread = threading.Thread(target=self._serve, name="gpmppi-spawner", daemon=True)
                self._thread.start()
        box: dict[str, Any] = {}
        done = threading.Event()
        self._requests.put((args, kwargs, box, done))
        done.wait()
        if "error" in box:
            raise box["error"]
        return box["process"]

    def _serve(self) -> None:
        while True:
            args, kwargs, box, done = self._requests.get()
            try:
                box["process"] = subprocess.Popen(*args, **kwargs)
            except BaseException as exc:  # noqa: BLE001 - raised in the caller's thread
                box["error"] = exc
            finally:
                done.set()


_SPAWNER = _Spawner()


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
    in_a_row: int = 0  # restarts since the last run that lasted restart_reset_s
    exited_at: float | None = None  # when the watcher saw the current process end (monotonic)
    hold_until: float = 0.0  # a crash restart waits at least until then (see Launcher.kill)


@dataclass
class RestartEvent:
    """One crash restart, for the summary."""

    name: str
    died_s: float  # since launch start [s]
    cause: str  # 'SIGKILL', 'exit code 1', ...
    uptime_s: float  # how long the process that died had run [s]
    delay_s: float  # backoff before the new process [s]
    note: str = ""


def exit_cause(code: int) -> str:
    """A process's return code in words: 'SIGKILL' (killed by a signal), 'exit code 1'."""
    if code < 0:
        try:
            return signal.Signals(-code).name
        except ValueError:
            return f"signal {-code}"
    return f"exit code {code}"


def _seconds(t: float) -> str:
    """0.1 -> '0.1', 0.25 -> '0.25', 2.0 -> '2'."""
    return f"{t:.2f}".rstrip("0").rstrip(".")


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
        self.restart_events: list[RestartEvent] = []
        # set by a process's watcher thread when it ends (and by request_stop): the supervision loop wakes at once
        self.wake = threading.Event()

    def child(self, name: str) -> Child:
        child = next((c for c in self.children if c.name == name), None)
        if child is None:
            raise KeyError(f"no service named {name!r}; running: {', '.join(c.name for c in self.children)}")
        return child

    def request_stop(self) -> None:
        self.stop_event.set()
        self.wake.set()

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
        # the child stops when this process dies, however it dies (services.run.follow_launcher)
        env[LAUNCHER_PID_ENV] = str(os.getpid())
        child.process = _SPAWNER.popen(
            [sys.executable, "-m", "services.run", child.kind, "--config", str(child.config_path)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env=env,
            cwd=os.getcwd(),
            start_new_session=True,  # Ctrl-C reaches only the launcher, which stops children in order
        )
        child.started_at = time.monotonic()
        child.exited_at = None
        child.first_started_at = child.first_started_at or child.started_at
        assert child.process.stdout is not None
        threading.Thread(target=self._pump, args=(child, child.process.stdout), daemon=True).start()
        threading.Thread(target=self._watch, args=(child, child.process), daemon=True).start()
        self.say("launch", f"started {child.name} ({child.kind}) pid {child.process.pid}")

    def _watch(self, child: Child, process: subprocess.Popen) -> None:
        """Wait on one process; when it ends, note when and wake the supervision loop (no polling delay)."""
        process.wait()
        if child.process is process:
            child.exited_at = time.monotonic()
        self.wake.set()

    def start_all(self) -> None:
        for child in self.children:
            self._spawn(child)
            if child.kind == "router":
                wait_for_endpoint(self.launch.router.listen[0], timeout_s=10.0)

    def supervise(self) -> float:
        """Restart crashed services with backoff; mark them failed after max_restarts in a row. Returns how
        long the caller may wait before the next call (the next restart due), at most 0.1 s."""
        with self._process_lock:
            return self._supervise(time.monotonic())

    def _supervise(self, now: float) -> float:
        next_due = 0.1
        for child in self.children:
            if child.failed or child.process is None:
                continue
            if child.restart_at is not None:
                if now >= child.restart_at:
                    child.restart_at = None
                    child.restarts += 1
                    if child.kind == "recorder" or (child.kind == "viewer" and self._saves_a_file(child)):
                        self._output_continues(child)
                    self._spawn(child)
                else:
                    next_due = min(next_due, child.restart_at - now)
                continue
            code = child.process.poll()
            if code is None:
                continue
            died = child.exited_at or now
            uptime = died - child.started_at
            child.exit_codes.append(code)
            cause = exit_cause(code)
            if uptime >= self.launch.restart_reset_s:
                child.in_a_row = 0  # it had run well: a new crash is not part of a crash loop
            if child.in_a_row >= self.launch.max_restarts:
                child.failed = True
                self.say("launch", f"{child.name} exited ({cause}) and has failed for good")
                if child.required:
                    self.request_stop()
                continue
            delay = min(8.0, self.launch.restart_backoff_s * 2**child.in_a_row)
            child.in_a_row += 1
            child.restart_at = max(died + delay, child.hold_until)
            delay = child.restart_at - died
            next_due = min(next_due, max(0.0, child.restart_at - now))
            self.restart_events.append(RestartEvent(child.name, died - self.t0, cause, uptime, delay))
            self.say(
                "launch",
                f"{child.name} exited ({cause}) after {uptime:.1f} s; "
                f"restart {child.restarts + 1} in {_seconds(delay)} s",
            )
        return next_due

    def _output_continues(self, child: Child) -> None:
        """A restarted recorder (or viewer saving a file) must not overwrite what its predecessor wrote: it
        continues in a new file, `<name>.restart<N><suffix>` (or the next free name, if that is taken)."""
        config = yaml.safe_load(child.config_path.read_text()) or {}
        default = "runs/recording.mcap" if child.kind == "recorder" else "runs/view.rrd"
        path = Path(config.get("path", default))
        stem = path.stem.split(".restart")[0]
        new = free_name(path.with_name(f"{stem}.restart{child.restarts}{path.suffix}"))
        config["path"] = str(new)
        child.config_path.write_text(yaml.safe_dump(config, sort_keys=False))
        if self.restart_events and self.restart_events[-1].name == child.name:
            self.restart_events[-1].note = f"continues in {new}"
        self.say("launch", f"{child.name}: {path} is kept as written; the restarted {child.kind} writes {new}")

    @staticmethod
    def _saves_a_file(child: Child) -> bool:
        config = yaml.safe_load(child.config_path.read_text()) or {}
        return config.get("mode", "save") == "save"

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
        try:
            p.send_signal(signal.SIGCONT)  # a frozen (SIGSTOP) process could not act on SIGINT
        except ProcessLookupError:
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
            child = self.child(name)
            if child.failed or child.restart_at is not None:
                raise RuntimeError(f"{name} is not running (failed or waiting for a crash restart)")
            self._stop(child)
            self._spawn(child)
            return child

    def kill(self, name: str, sig: signal.Signals = signal.SIGKILL, restart_after_s: float | None = None) -> Child:
        """A fault on purpose (fault tests, drills): send `sig` to a running service. Supervision treats a death
        like any crash; `restart_after_s` keeps the service down at least that long (an outage of known length)."""
        with self._process_lock:
            child = self.child(name)
            if child.process is None or child.process.poll() is not None:
                raise RuntimeError(f"{name} is not running")
            if restart_after_s is not None:
                child.hold_until = time.monotonic() + restart_after_s
            child.process.send_signal(sig)
            self.say("launch", f"sent {sig.name} to {name} (pid {child.process.pid})")
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
