"""The launcher's process bookkeeping: what it keeps about each service (`Child`) and each of its processes (`Proc`),
its crash restarts (`RestartEvent`), the one thread that starts every child process (`SPAWNER`), an exit code in
words, a service's log line made readable and the wait for the router's endpoint (`services.launch.supervisor`
uses them)."""

from __future__ import annotations

import json
import queue
import signal
import socket
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


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


SPAWNER = _Spawner()


@dataclass
class Proc:
    """One process of a service: its Popen, the launcher's end of its role socket (services.runtime.role), when
    it started and when it said it was ready (everything loaded, waiting for its go) [monotonic s]."""

    process: subprocess.Popen
    sock: socket.socket | None
    started_at: float
    label: str  # its log lines' prefix: the service's name, or `name*` while it is a spare
    ready_at: float | None = None

    def close(self) -> None:
        if self.sock is not None:
            try:
                self.sock.close()
            except OSError:
                pass


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
    proc: Proc | None = None  # the current process's role socket and ready time
    spare: Proc | None = None  # its warm spare, if it has one now
    spare_due: float | None = None  # when the next spare is made (monotonic; None: no spare wanted)
    spare_deaths: int = 0  # spares that died in a row (each doubles the wait for the next)
    takeovers: int = 0


@dataclass
class RestartEvent:
    """One crash restart, for the summary."""

    name: str
    died_s: float  # since launch start [s]
    cause: str  # 'SIGKILL', 'exit code 1', ...
    uptime_s: float  # how long the process that died had run [s]
    delay_s: float  # backoff before the new process [s]; for a takeover, from the death to the spare's go
    note: str = ""
    takeover_pid: int | None = None  # the warm spare that took over (None: a new process was started)


def exit_cause(code: int) -> str:
    """A process's return code in words: 'SIGKILL' (killed by a signal), 'exit code 1'."""
    if code < 0:
        try:
            return signal.Signals(-code).name
        except ValueError:
            return f"signal {-code}"
    return f"exit code {code}"


def seconds_text(t: float) -> str:
    """0.1 -> '0.1', 0.25 -> '0.25', 2.0 -> '2'."""
    return f"{t:.2f}".rstrip("0").rstrip(".")


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
    """Wait until a tcp/<host>:<port> or tls/<host>:<port> endpoint accepts connections (TLS runs over TCP, so its
    port is probed the same way); any other kind of endpoint is given 0.5 s."""
    import socket

    kind, _, address = endpoint.partition("/")
    if kind not in ("tcp", "tls"):
        time.sleep(0.5)
        return
    host, port = address.rsplit(":", 1)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.create_connection((host, int(port)), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"the router did not open {endpoint} within {timeout_s} s")
