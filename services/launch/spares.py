"""The launcher's warm spares (docs/faults.md): for each critical service (`SPARE_KINDS`, or the launch file's
`spares`) a second process started ahead of need, which takes over at once when its service dies. `WarmSpares` is
the part of `services.launch.supervisor.Launcher` that makes, replaces, hands over and stops them."""

from __future__ import annotations

import signal
import subprocess
import threading
from typing import TYPE_CHECKING

from services.launch.processes import Child, Proc, RestartEvent, exit_cause, seconds_text
from services.runtime.role import JOINED

if TYPE_CHECKING:
    from services.launch.launch_file import LaunchFile

# the control path, most critical first: the services that get a warm spare by default, in the order spares are made
SPARE_KINDS = ("planner", "terrain", "ingress", "egress")


class WarmSpares:
    """The warm spares of a launcher's services (a base of `Launcher`, which owns the processes): made one at a time
    once their service runs, replaced when they die, given the go when their service dies, stopped first."""

    # the launcher's, used here (`services.launch.supervisor.Launcher`)
    launch: LaunchFile
    children: list[Child]
    stop_event: threading.Event
    _process_lock: threading.RLock
    t0: float
    restart_events: list[RestartEvent]

    def _init_spares(self, names: list[str] | None) -> None:
        """No spare yet; `names`: the launch file's `spares` (None: every service of a kind in `SPARE_KINDS`)."""
        self.spare_events: list[str] = []  # a spare's death, for the summary
        self.spares_at_stop: dict[str, int] = {}  # service -> pid of its spare when the launch stopped
        self._spare_names = None if names is None else set(names)

    if TYPE_CHECKING:  # the launcher's methods used here, declared for the type checker only

        def say(self, name: str, line: str) -> None: ...

        def child(self, name: str) -> Child: ...

        def _start_process(self, child: Child, label: str, spare: bool = False) -> Proc: ...

        def _go(self, child: Child, proc: Proc) -> None: ...

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
                     f"{now - self.t0:.1f} s; a new one in {seconds_text(wait)} s")
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
            child.spare = self._start_process(child, f"{child.name}*", spare=True)
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
                                   f"{seconds_text(timeout)} s of its go; killing it")
                proc.process.send_signal(signal.SIGCONT)
                proc.process.kill()

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
