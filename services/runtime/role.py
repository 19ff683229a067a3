"""When a launcher-started process may join, and what its predecessor left: the launcher's side of a service's
start, seen from the service's process.

The launcher (`services.launch.supervisor`) starts every service process with one end of a socket pair, its file
descriptor in `GPMPPI_ROLE_FD`. The process does what it can before it joins (imports, the model file, its
compiled kernels), then `Node.open` calls `wait_for_role`, which says "ready" on the socket and blocks on it (a
read: no CPU) until the launcher answers with one JSON line, the go:

    {"handover": {"plan": "<the last Plan payload the launcher saw>", ...}}

A process started as the service gets its go at once; a warm spare gets it when the service it backs has died.
Only the launcher knows which it was: the service module runs the same code either way. `handover` holds the
last payload the launcher's own session received on the keys the service resumes from (the planner's last Plan,
the terrain service's last weights), by registered key name; a service without a predecessor gets none.

Outside a launcher (by hand, systemd) there is no socket: `wait_for_role` returns None at once. Under systemd a
process with `GPMPPI_STANDBY=1` stands by instead (`Node.open`): it joins, keeps the last payload on the same keys,
and declares itself only once no other process of its service is alive (deploy/systemd/README.md).
"""

from __future__ import annotations

import json
import os
import select
import socket
import threading
import time
from dataclasses import dataclass, field

from services.runtime.session import StoppedWhileWaiting
from services.runtime.spare_priority import restore_at_go

ROLE_FD_ENV = "GPMPPI_ROLE_FD"
STANDBY_ENV = "GPMPPI_STANDBY"
READY = b"ready\n"
JOINED = b"joined\n"
# what a service resumes from, by kind: registered key name -> key under gpmppi/{robot}/ (the launcher's own session,
# or a standby's, keeps the last payload on each and hands it to the next process of that service)
HANDOVER: dict[str, dict[str, str]] = {"planner": {"plan": "plan"}, "terrain": {"terrain_weights": "terrain/weights"}}


def standby_requested() -> bool:
    """`GPMPPI_STANDBY=1`: outside a launcher, join only once no other process of this service is alive."""
    return os.environ.get(STANDBY_ENV, "").lower() in ("1", "true", "yes")


def notify_systemd_ready() -> None:
    """Tell systemd this service is up (`Type=notify` units; nothing without `NOTIFY_SOCKET`)."""
    address = os.environ.get("NOTIFY_SOCKET", "")
    if not address:
        return
    if address.startswith("@"):
        address = "\0" + address[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
            sock.sendto(b"READY=1", address)
    except OSError:
        pass


@dataclass
class Role:
    """The launcher's go: what the predecessor left (registered key name -> payload), and how long this process
    waited for it after it was ready [s]."""

    handover: dict[str, bytes] = field(default_factory=dict)
    waited_s: float = 0.0
    priority_note: str | None = None  # a spare that could not take its service's CPU priority back: why


_taken: Role | None = None


def wait_for_role(stop: threading.Event | None = None) -> Role | None:
    """Tell the launcher this process is ready, and wait for its go (None without a launcher's socket). The first
    call waits; later calls return the same role. `StoppedWhileWaiting` when `stop` is set meanwhile (SIGINT,
    SIGTERM) or the launcher closed its end (it stops, or it died)."""
    global _taken
    if _taken is not None:
        return _taken
    fd = os.environ.get(ROLE_FD_ENV, "")
    if not fd.isdigit():
        return None
    os.environ.pop(ROLE_FD_ENV)  # not for this process's own children (compile_ahead, ...)
    sock = socket.socket(fileno=int(fd))
    try:
        t0 = time.monotonic()
        try:
            sock.sendall(READY)
        except OSError as exc:
            raise StoppedWhileWaiting(f"the launcher is gone ({exc})") from None
        buf = b""
        while b"\n" not in buf:
            if stop is not None and stop.is_set():
                raise StoppedWhileWaiting("stopped while waiting for the launcher's go")
            # blocked in the kernel; the timeout only lets a stop (a signal handler setting `stop`) be seen
            ready, _, _ = select.select([sock], [], [], 1.0)
            if not ready:
                continue
            chunk = sock.recv(1 << 16)
            if not chunk:
                raise StoppedWhileWaiting("the launcher closed its end before its go")
            buf += chunk
        go = json.loads(buf.split(b"\n", 1)[0])
        handover = {str(k): str(v).encode() for k, v in (go.get("handover") or {}).items()}
        _taken = Role(handover, time.monotonic() - t0, restore_at_go())
        global _joined_to
        _joined_to, sock = sock, None  # kept open for `say_joined`
        return _taken
    finally:
        if sock is not None:
            sock.close()


_joined_to: socket.socket | None = None


def say_joined() -> None:
    """Tell the launcher this process has joined as its service (its liveliness token is declared): a spare that
    got its go but never says so (frozen, stuck) is replaced."""
    global _joined_to
    if _joined_to is None:
        return
    try:
        _joined_to.sendall(JOINED)
    except OSError:
        pass
    finally:
        _joined_to.close()
        _joined_to = None


def go_message(handover: dict[str, bytes]) -> bytes:
    """The launcher's go line for `handover` (registered key name -> payload, JSON text)."""
    return json.dumps({"handover": {k: v.decode() for k, v in handover.items()}}).encode() + b"\n"
