"""The launcher's supervision: each service a child process, its output prefixed, its death seen at once (a
thread waits on each process) and answered by its warm spare taking over, or with a restart after a backoff; a stop
in reverse order. `services.launch.launcher` builds a `Launcher` from a launch file and runs it.

Warm spares (docs/faults.md): for each critical service (`SPARE_KINDS`, or the launch file's `spares`) a second
process is started ahead of need. Every service process gets a role socket (`services.runtime.role`): it loads what
it can, says "ready" and waits for the launcher's go, which a service's own process gets at once and a spare when
its service has died, with the last payloads on the keys the service resumes from (`HANDOVER`). The service modules
run the same code either way. The spares' part is `services.launch.spares`; what is kept about each service and
process, `services.launch.processes`."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import yaml

from services.launch.processes import (
    SPAWNER,
    Child,
    Proc,
    RestartEvent,
    exit_cause,
    readable,
    seconds_text,
    wait_for_endpoint,
)
from services.launch.spares import WarmSpares
from services.recording.output_files import free_name
from services.run import LAUNCHER_PID_ENV, SERVICES
from services.runtime.role import HANDOVER, READY, ROLE_FD_ENV, go_message
from services.runtime.spare_priority import SPARE_NICE_ENV

if TYPE_CHECKING:
    from services.launch.launch_file import LaunchFile

REPO_ROOT = Path(__file__).resolve().parents[2]


class Launcher(WarmSpares):
    """The launch's child processes: started in order, supervised (a death answered by its warm spare taking over,
    or a restart after a backoff), stopped in reverse order; the warm spares' part is `WarmSpares`."""

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
        # the last payload the launcher's own session saw on a key (gpmppi/{robot}/...), for a handover; set by
        # whoever holds that session (the launcher's Monitor)
        self.last_payload: Callable[[str], bytes | None] | None = None
        self._init_spares(launch.spares)

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

    def _pump(self, proc: Proc, stream: IO[bytes]) -> None:
        for raw in iter(stream.readline, b""):
            self.say(proc.label, readable(raw.decode(errors="replace")))
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

    def _start_process(self, child: Child, label: str, spare: bool = False) -> Proc:
        """A new process of `child`'s service with a role socket (services.runtime.role): it loads what it can,
        says it is ready and waits for its go (`_go`); `spare`: a warm spare, which starts at a lower CPU priority
        (`LaunchFile.spare_nice`, services.runtime.spare_priority)."""
        env = dict(os.environ)
        env.pop(SPARE_NICE_ENV, None)
        if spare and self.launch.spare_nice:
            env[SPARE_NICE_ENV] = str(self.launch.spare_nice)
        env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
        env["PYTHONUNBUFFERED"] = "1"
        # the child stops when this process dies, however it dies (services.run.follow_launcher)
        env[LAUNCHER_PID_ENV] = str(os.getpid())
        ours: socket.socket | None = None
        theirs: socket.socket | None = None
        pass_fds: tuple[int, ...] = ()
        if child.kind != "router":
            ours, theirs = socket.socketpair()
            env[ROLE_FD_ENV] = str(theirs.fileno())
            pass_fds = (theirs.fileno(),)
        try:
            process = SPAWNER.popen(
                [sys.executable, "-m", "services.run", child.kind, "--config", str(child.config_path)],
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                env=env,
                cwd=os.getcwd(),
                start_new_session=True,  # Ctrl-C reaches only the launcher, which stops children in order
                pass_fds=pass_fds,
            )
        finally:
            if theirs is not None:
                theirs.close()
        proc = Proc(process, ours, time.monotonic(), label)
        assert process.stdout is not None
        threading.Thread(target=self._pump, args=(proc, process.stdout), daemon=True).start()
        threading.Thread(target=self._watch, args=(child, process), daemon=True).start()
        if ours is not None:
            threading.Thread(target=self._await_ready, args=(proc,), daemon=True).start()
        return proc

    def _await_ready(self, proc: Proc) -> None:
        """Note when the process says it is ready (loaded, waiting for its go); wakes the supervision loop."""
        assert proc.sock is not None
        try:
            said = proc.sock.recv(len(READY))
        except OSError:
            return
        if said == READY:
            proc.ready_at = time.monotonic()
            self.wake.set()

    def _go(self, child: Child, proc: Proc) -> None:
        """Let `proc` join as `child`'s service, with the last payloads on the keys it resumes from (on a thread of
        its own: a large handover must not block supervision on a process that has not read it yet)."""
        if proc.sock is None:
            return
        handover: dict[str, bytes] = {}
        if self.last_payload is not None:
            for name, key in HANDOVER.get(child.kind, {}).items():
                payload = self.last_payload(f"gpmppi/{self.launch.robot}/{key}")
                if payload is not None:
                    handover[name] = payload
        line = go_message(handover)
        sock = proc.sock

        def send() -> None:
            try:
                sock.sendall(line)
            except OSError:
                pass  # it died meanwhile: supervision sees that

        threading.Thread(target=send, daemon=True).start()

    def _spawn(self, child: Child) -> None:
        if child.proc is not None:
            child.proc.close()
        proc = self._start_process(child, child.name)
        self._go(child, proc)
        child.proc = proc
        child.process = proc.process
        child.started_at = proc.started_at
        child.exited_at = None
        child.first_started_at = child.first_started_at or child.started_at
        if self.wants_spare(child) and child.spare is None:
            child.spare_due = child.started_at + self.launch.spare_delay_s
        self.say("launch", f"started {child.name} ({child.kind}) pid {proc.process.pid}")

    def _watch(self, child: Child, process: subprocess.Popen) -> None:
        """Wait on one process; when it ends, note when and wake the supervision loop (no polling delay)."""
        process.wait()
        if child.process is process:
            child.exited_at = time.monotonic()
        self.wake.set()

    def start_all(self) -> None:
        self.check_spares()
        for child in self.children:
            self._spawn(child)
            if child.kind == "router":
                for listener in self.launch.router.listen:  # each one: a client may connect over any of them
                    wait_for_endpoint(listener, timeout_s=10.0)

    def supervise(self) -> float:
        """Restart crashed services with backoff; mark them failed after max_restarts in a row. Returns how
        long the caller may wait before the next call (the next restart due), at most 0.1 s."""
        with self._process_lock:
            return self._supervise(time.monotonic())

    def _supervise(self, now: float) -> float:
        next_due = 0.1
        self._tend_spares(now)
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
            if child.in_a_row == 0 and self._take_over(child, died, cause, uptime, now):
                continue  # a second death in a row restarts with backoff, below
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
                f"restart {child.restarts + 1} in {seconds_text(delay)} s",
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
        """The spares first (they hold no session and no file: SIGTERM, then SIGKILL); then the services in reverse
        start order: SIGINT, wait, SIGTERM, wait, SIGKILL."""
        with self._process_lock:
            self._stop_spares()
            for child in reversed(self.children):
                self._stop(child)
                if child.proc is not None:
                    child.proc.close()

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


