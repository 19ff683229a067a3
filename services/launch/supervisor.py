"""The launcher's supervision: each service a child process, its output prefixed, its death seen at once (a
thread waits on each process) and answered by its warm spare taking over, or with a restart after a backoff; a stop
in reverse order. `services.launch.launcher` builds a `Launcher` from a launch file and runs it.

Warm spares (docs/faults.md): for each critical service (`SPARE_KINDS`, or the launch file's `spares`) a second
process is started ahead of need. Every service process gets a role socket (`services.runtime.role`): it loads what
it can, says "ready" and waits for the launcher's go, which a service's own process gets at once and a spare when
its service has died, with the last payloads on the keys the service resumes from (`HANDOVER`). The service modules
run the same code either way."""

from __future__ import annotations

import json
import os
import queue
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import yaml

from services.recording.output_files import free_name
from services.run import LAUNCHER_PID_ENV, SERVICES
from services.runtime.role import HANDOVER, JOINED, READY, ROLE_FD_ENV, go_message

if TYPE_CHECKING:
    from services.launch.launch_file import LaunchFile

REPO_ROOT = Path(__file__).resolve().parents[2]

# the control path, most critical first: the services that get a warm spare by default, in the order spares are made
SPARE_KINDS = ("planner", "terrain", "ingress", "egress")


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
        # the last payload the launcher's own session saw on a key (gpmppi/{robot}/...), for a handover; set by
        # whoever holds that session (the launcher's Monitor)
        self.last_payload: Callable[[str], bytes | None] | None = None
        self.spare_events: list[str] = []  # a spare's death, for the summary
        self.spares_at_stop: dict[str, int] = {}  # service -> pid of its spare when the launch stopped
        names = launch.spares
        self._spare_names = None if names is None else set(names)

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

    def _start_process(self, child: Child, label: str) -> Proc:
        """A new process of `child`'s service with a role socket (services.runtime.role): it loads what it can,
        says it is ready and waits for its go (`_go`)."""
        env = dict(os.environ)
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
            process = _SPAWNER.popen(
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

    def _await_joined(self, child: Child, proc: Proc) -> None:
        """A spare that got its go must join (declare itself) within `takeover_timeout_s`; one that does not (frozen,
        stuck) is killed, and supervision restarts its service with backoff like any second death in a row."""
        assert proc.sock is not None
        timeout = self.launch.takeover_timeout_s
        try:
            proc.sock.settimeout(timeout)
            said = proc.sock.recv(len(JOINED))
        except TimeoutError:
            said = b""
        except OSError:
            return  # closed: the launch is stopping, or the process died (supervision sees that)
        if said == JOINED or self.stop_event.is_set():
            return
        with self._process_lock:
            if child.process is proc.process and proc.process.poll() is None:
                self.say("launch", f"{child.name}: its spare (pid {proc.process.pid}) did not join within "
                                   f"{_seconds(timeout)} s of its go; killing it")
                proc.process.send_signal(signal.SIGCONT)
                proc.process.kill()

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

    # ---- warm spares ----------------------------------------------------------------------------
    def wants_spare(self, child: Child) -> bool:
        """Whether `child` gets a warm spare (the launch file's `spares`)."""
        if self._spare_names is None:
            return child.kind in SPARE_KINDS
        return child.name in self._spare_names

    def _tend_spares(self, now: float) -> None:
        """Replace a spare that died (after a wait that doubles while they keep dying), and make the spares that
        are due, one warming at a time, the most critical service first."""
        for child in self.children:
            spare = child.spare
            if spare is None or (code := spare.process.poll()) is None:
                continue
            child.spare = None
            spare.close()
            child.spare_deaths += 1
            wait = min(60.0, max(1.0, self.launch.spare_delay_s) * 2 ** (child.spare_deaths - 1))
            child.spare_due = now + wait
            event = (f"{child.name}'s spare (pid {spare.process.pid}) died ({exit_cause(code)}) at "
                     f"{now - self.t0:.1f} s; a new one in {_seconds(wait)} s")
            self.spare_events.append(event)
            self.say("launch", event)
        for child in self.children:
            if child.spare is not None and child.spare.ready_at is not None and child.spare_deaths:
                child.spare_deaths = 0  # it got ready: the next one that dies waits the base delay again
        if any(c.spare is not None and c.spare.ready_at is None for c in self.children):
            return  # one warming at a time
        if any(c.proc is not None and c.proc.sock is not None and c.proc.ready_at is None and c.process is not None
               and c.process.poll() is None for c in self.children):
            return  # a service is (re)starting: it has the CPU first
        order = {kind: i for i, kind in enumerate(SPARE_KINDS)}
        for child in sorted(self.children, key=lambda c: order.get(c.kind, len(order))):
            if child.spare is not None or child.spare_due is None or now < child.spare_due:
                continue
            if child.failed or child.restart_at is not None or child.process is None:
                continue
            if child.process.poll() is not None or self.stop_event.is_set():
                continue
            child.spare = self._start_process(child, f"{child.name}*")
            child.spare_due = None
            self.say("launch", f"started a warm spare for {child.name} ({child.kind}) pid {child.spare.process.pid}")
            return

    def _take_over(self, child: Child, died: float, cause: str, uptime: float, now: float) -> bool:
        """`child` died: its ready spare, if it has one, takes over at once (its go). False: none could."""
        spare = child.spare
        if spare is None or spare.ready_at is None or spare.process.poll() is not None:
            return False
        if now < child.hold_until:
            return False  # kept down on purpose (`kill(..., restart_after_s)`): the restart waits for it
        child.spare = None
        self._go(child, spare)
        threading.Thread(target=self._await_joined, args=(child, spare), daemon=True).start()
        spare.label = child.name
        old = child.proc
        if old is not None:
            old.close()
        child.proc = spare
        child.process = spare.process
        child.started_at = now
        child.exited_at = None
        child.restarts += 1
        child.in_a_row += 1
        child.takeovers += 1
        child.spare_due = now + self.launch.spare_delay_s
        event = RestartEvent(child.name, died - self.t0, cause, uptime, now - died,
                             takeover_pid=spare.process.pid)
        self.restart_events.append(event)
        self.say("launch", f"{child.name} exited ({cause}) after {uptime:.1f} s; its warm spare pid "
                           f"{spare.process.pid} takes over ({(now - died) * 1e3:.0f} ms after the death)")
        return True

    def _watch(self, child: Child, process: subprocess.Popen) -> None:
        """Wait on one process; when it ends, note when and wake the supervision loop (no polling delay)."""
        process.wait()
        if child.process is process:
            child.exited_at = time.monotonic()
        self.wake.set()

    def check_spares(self) -> None:
        """The launch file's `spares` name services of this launch whose kind can have one: ValueError otherwise (a
        recorder's spare would write over its predecessor's file, a sim's would start the robot from its start pose)."""
        if self._spare_names is None:
            return
        kinds = {c.name: c.kind for c in self.children}
        for name in sorted(self._spare_names):
            if name not in kinds:
                raise ValueError(f"spares names {name!r}, which this launch does not run; it runs "
                                 f"{', '.join(kinds)}")
            if kinds[name] not in SPARE_KINDS:
                raise ValueError(f"spares names {name!r}, a {kinds[name]}: only {', '.join(SPARE_KINDS)} services "
                                 "can have a warm spare")

    def start_all(self) -> None:
        self.check_spares()
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
        """The spares first (they hold no session and no file: SIGTERM, then SIGKILL); then the services in reverse
        start order: SIGINT, wait, SIGTERM, wait, SIGKILL."""
        with self._process_lock:
            self._stop_spares()
            for child in reversed(self.children):
                self._stop(child)
                if child.proc is not None:
                    child.proc.close()

    def _stop_spares(self) -> None:
        spares = [(c, c.spare) for c in self.children if c.spare is not None]
        self.spares_at_stop = {c.name: sp.process.pid for c, sp in spares if sp is not None}
        for _, spare in spares:
            assert spare is not None
            spare.close()  # a spare waiting for its go sees the socket close and exits
            try:
                spare.process.send_signal(signal.SIGCONT)
                spare.process.send_signal(signal.SIGTERM)
            except ProcessLookupError:
                pass
        for child, spare in spares:
            assert spare is not None
            try:
                spare.process.wait(self.launch.stop_timeout_s)
            except subprocess.TimeoutExpired:
                spare.process.kill()
                spare.process.wait()
            child.spare = None
            self.say("launch", f"stopped {child.name}'s spare (exit {spare.process.returncode})")

    def kill_spare(self, name: str, sig: signal.Signals = signal.SIGKILL) -> int:
        """A fault on purpose: send `sig` to the spare of `name` (its pid); supervision replaces a spare that dies."""
        with self._process_lock:
            spare = self.child(name).spare
            if spare is None or spare.process.poll() is not None:
                raise RuntimeError(f"{name} has no spare running")
            spare.process.send_signal(sig)
            self.say("launch", f"sent {sig.name} to {name}'s spare (pid {spare.process.pid})")
            return spare.process.pid

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
