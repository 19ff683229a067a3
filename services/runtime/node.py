"""The shared runtime of every gpmppi service: Zenoh session, typed pub/sub, heartbeat, logs (the settings every
service shares are in `services.runtime.node_settings`).

A service is a short event loop over a `Node`:

    node = Node(settings)            # nothing networked yet
    with node:                       # opens the Zenoh session (after the process started, never across a fork)
        pub = node.publisher("cmd")
        sub = node.subscribe("state")            # newest-only by default (FIFO on request)
        while node.ok():                         # False after SIGINT/SIGTERM
            msg = sub.take()                     # decoded + validated, or None; bad input counted, never raised
            ...
            node.spin_once()                     # heartbeat at `heartbeat_hz`; waits until input arrives (or poll_s)

Input wakes the loop at once (a Zenoh callback fills the subscription's inbox and sets an event the loop waits
on), so a message on the control path waits for no polling interval.

Sessions are Zenoh clients of a router (the launcher starts one; `zenohd` works too) or listening peers.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from types import TracebackType
from typing import Generic, TypeVar

import zenoh

from schemas import KEYS, DecodeError, Heartbeat, Message, decode, encode, key_for
from schemas.codec import ENCODING
from services.runtime.config_file import ConfigFileError
from services.runtime.counters import Counters
from services.runtime.liveliness import LIVELINESS_PREFIX, stand_by, wait_while_alive
from services.runtime.node_settings import NodeSettings, changed_since_loaded
from services.runtime.role import notify_systemd_ready, say_joined, standby_requested, wait_for_role
from services.runtime.scheduling import Inbox
from services.runtime.session import open_session
from services.runtime.signals import StopSignals

M = TypeVar("M", bound=Message)


class SettingsChanged(RuntimeError):
    """A process that was started ahead of need found, when it was to take over, that its settings file says
    otherwise than what it loaded at its start."""


# ---- typed pub/sub ----------------------------------------------------------------------------
class TypedPublisher(Generic[M]):
    """Publishes one message type on one key; JSON with `application/json` encoding; validated before sending."""

    def __init__(self, node: Node, key: str, model: type[M], publisher: zenoh.Publisher) -> None:
        self.node = node
        self.key = key
        self.model = model
        self._publisher = publisher
        self._seq = 0

    def put(self, msg: M, attachment: bytes | None = None) -> None:
        if not isinstance(msg, self.model):
            raise TypeError(f"{self.key} carries {self.model.__name__}, not {type(msg).__name__}")
        msg.header.seq = self._seq
        payload = encode(msg)
        # re-validate what goes out (fields may have been assigned after construction): never send NaN/inf
        decode(self.model, payload, self.node.settings.max_payload_bytes)
        self._publisher.put(payload, attachment=attachment)
        self._seq += 1
        with self.node.counters.lock:
            self.node.counters.published += 1


class TypedSubscription(Generic[M]):
    """Receives one message type; bad payloads are counted, logged and dropped (never raised).

    Every payload that arrives is decoded once: by the loop when it takes it, or, newest-only, on Zenoh's callback
    thread when a newer one replaced it before the loop took it (`Inbox`), so that a bad message is counted and
    logged whatever the loop's timing. The planner's state inbox (states at 50 Hz, a plan taking tens of ms) had
    lost bad states that way, uncounted; the loop still plans from the newest state only."""

    def __init__(
        self, node: Node, key: str, model: type[M], newest_only: bool, capacity: int, remote_only: bool = False
    ) -> None:
        self.node = node
        self.key = key
        self.model = model
        self._inbox = node.inbox(key, newest_only, capacity, remote_only,
                                 on_displaced=self._decode if newest_only else None)
        self.last: M | None = None  # the newest valid message the loop took

    def _decode(self, sample: zenoh.Sample) -> M | None:
        """The message, or None for a bad payload (counted and logged); on the loop's thread or Zenoh's."""
        counters = self.node.counters
        with counters.lock:
            counters.received += 1
        try:
            return decode(self.model, sample.payload.to_bytes(), self.node.settings.max_payload_bytes)
        except DecodeError as exc:
            self.node.reject(f"{sample.key_expr}: {exc}")
            return None

    def take(self) -> M | None:
        """The newest valid message since the last call, or None (newest-only: at most one is queued)."""
        newest = None
        while (sample := self._inbox.take()) is not None:
            msg = self._decode(sample)
            newest = msg if msg is not None else newest
        if newest is not None:
            self.last = newest
        return newest

    def drain(self, limit: int = 10_000) -> list[M]:
        """Every valid queued message, oldest first."""
        out: list[M] = []
        while len(out) < limit and (sample := self._inbox.take()) is not None:
            msg = self._decode(sample)
            if msg is not None:
                out.append(msg)
        if out:
            self.last = out[-1]
        return out


# ---- the node ---------------------------------------------------------------------------------
class Node:
    """One service's connection to the rest: session, token, heartbeat, counters, stop flag."""

    def __init__(self, settings: NodeSettings, install_signals: bool = True) -> None:
        self.settings = settings
        self.name = settings.service
        self.log = logging.getLogger(f"gpmppi.{self.name}")
        self.counters = Counters()
        self.session: zenoh.Session | None = None
        self._stop = threading.Event()
        self._wake = threading.Event()  # set by arriving input and by stop: ends the loop's idle wait
        self.closing = False
        self._subscribers: list[zenoh.Subscriber] = []
        self._token: zenoh.LivelinessToken | None = None
        self._health: TypedPublisher[Heartbeat] | None = None
        self._next_heartbeat = 0.0
        self._cycle_times: deque[float] = deque(maxlen=512)
        self._reject_log_times: deque[float] = deque(maxlen=20)
        self.started = time.monotonic()
        # what a predecessor left, from the launcher's go (registered key name -> payload; `handed_over`)
        self.handover: dict[str, bytes] = {}
        self.zid = ""
        # the node's process stops on SIGINT / SIGTERM (never set from the handler itself: `StopSignals`)
        self._signals: StopSignals | None = None
        if install_signals and threading.current_thread() is threading.main_thread():
            self._signals = StopSignals(self._on_signal)

    # lifecycle
    def _on_signal(self, signum: int) -> None:
        self.log.info("signal %s: stopping", signal.Signals(signum).name)
        self.stop()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()

    def wake(self) -> None:
        """End the loop's current idle wait (input arrived)."""
        self._wake.set()

    def ok(self) -> bool:
        return not self._stop.is_set()

    def open(self) -> Node:
        if self.session is not None:
            return self
        # started by a launcher: everything before this line (imports, model, kernels) is done; the launcher says
        # when to join (at once, or, for a warm spare, when the service it backs died) and hands over what the
        # predecessor published last (services.runtime.role)
        role = wait_for_role(self._stop)
        if role is not None:
            self._settings_still_current()
            self.handover = dict(role.handover)
            if role.priority_note is not None:
                self.log.warning(role.priority_note)
            if role.waited_s > 1.0:
                self.log.info("taking over", extra={"fields": {"waited_s": round(role.waited_s, 1),
                                                               "handover": sorted(self.handover)}})
        # a client waits for its router (services start in any order); a stop meanwhile ends the wait
        self.session = open_session(self.settings.zenoh, self.log, self._stop)
        self.zid = str(self.session.zid())  # this process's identity on the wire (e.g. `Command.source`)
        robot, service = self.settings.robot, self.name
        token_key = LIVELINESS_PREFIX.format(robot=robot, service=service)
        if role is not None:
            # never two of one service publishing: liveliness decides, not the launcher's view of its processes
            wait_while_alive(self.session, token_key, self.name, self.log, self._stop)
        elif standby_requested():
            self.handover = stand_by(self.session, token_key, self.settings.robot, self.name, self.log, self._stop,
                                     self._wake)
            self._settings_still_current()
        self._token = self.session.liveliness().declare_token(token_key)
        say_joined()
        notify_systemd_ready()
        self._health = self.publisher("health")
        self.log.info(
            "session open", extra={"fields": {"zid": str(self.session.zid()), "mode": self.settings.zenoh.mode}}
        )
        return self

    def _settings_still_current(self) -> None:
        """Settings are read at the takeover, not only when the process started: a spare that loaded its settings
        before they were changed must not take over with the old ones. It exits instead (`SettingsChanged`), and the
        service restarts with the new ones, as a service restarted after a change does. A file that no longer loads
        leaves the settings loaded at the start (a restart would fail on it: the robot is better served by them)."""
        try:
            changed = changed_since_loaded(self.settings)
        except (ConfigFileError, ValueError, OSError) as exc:
            self.log.warning("the settings file no longer loads (%s): taking over with the settings loaded at the "
                             "start", exc)
            return
        if changed:
            raise SettingsChanged(f"{self.name}: the settings changed since this process loaded them "
                                  f"({', '.join(changed)}): exiting, so that the service restarts with them")

    def handed_over(self, name: str, model: type[M]) -> M | None:
        """The predecessor's last message on the registered key `name`, as the launcher saw it, or None."""
        payload = self.handover.get(name)
        if payload is None:
            return None
        try:
            return decode(model, payload, self.settings.max_payload_bytes)
        except DecodeError as exc:
            self.log.warning("handed-over %s not used: %s", name, exc)
            return None

    def close(self) -> None:
        if self.session is None:
            return
        self.closing = True
        try:
            self.heartbeat()
            if self._token is not None:
                self._token.undeclare()
            # callback subscribers first: closing a session with Python callbacks still declared can wait out
            # zenoh's close timeout (10 s) while a callback holds on; the inboxes drop what still arrives (closing)
            for sub in self._subscribers:
                try:
                    sub.undeclare()
                except Exception as e:  # already gone with a broken link: the close below still runs
                    self.log.debug("undeclaring a subscriber: %s", e)
            self.session.close()
        finally:
            self.session = None
            self._subscribers.clear()
            self.log.info("session closed")

    def __enter__(self) -> Node:
        return self.open()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc is not None and not isinstance(exc, KeyboardInterrupt):
            self.error(f"{type(exc).__name__}: {exc}")
        self.close()

    # pub/sub
    def key(self, name: str) -> str:
        return key_for(name, self.settings.robot, self.name)

    def publisher(self, name: str, key: str | None = None, model: type[M] | None = None) -> TypedPublisher[M]:
        """A typed publisher on the registered key `name` (or an explicit key and model)."""
        if self.session is None:
            raise RuntimeError("open the node (with node: ...) before declaring publishers")
        key = key or self.key(name)
        model = model or KEYS[name][1]  # type: ignore[assignment]
        pub = self.session.declare_publisher(key, encoding=zenoh.Encoding(ENCODING))
        return TypedPublisher(self, key, model, pub)  # type: ignore[arg-type]

    def subscribe(
        self,
        name: str,
        newest_only: bool = True,
        capacity: int = 1024,
        key: str | None = None,
        model: type[M] | None = None,
        remote_only: bool = False,
    ) -> TypedSubscription[M]:
        """A typed subscription; newest-only or FIFO (see `Inbox`); `remote_only` ignores this node's own."""
        if self.session is None:
            raise RuntimeError("open the node (with node: ...) before declaring subscriptions")
        key = key or self.key(name)
        model = model or KEYS[name][1]  # type: ignore[assignment]
        return TypedSubscription(self, key, model, newest_only, capacity, remote_only)  # type: ignore[arg-type]

    def inbox(self, key: str, newest_only: bool = True, capacity: int = 1024, remote_only: bool = False,
              on_displaced: Callable[[zenoh.Sample], object] | None = None) -> Inbox:
        """Raw samples on `key` (any key expression), waking the loop on arrival; see `Inbox` (`on_displaced`:
        newest-only, called with each sample a newer one replaced before the loop took it)."""
        if self.session is None:
            raise RuntimeError("open the node (with node: ...) before declaring subscriptions")
        inbox = Inbox(self.wake, lambda: self.closing, newest_only, capacity, on_displaced)
        origin = zenoh.Locality.REMOTE if remote_only else zenoh.Locality.ANY
        self._subscribers.append(
            self.session.declare_subscriber(key, zenoh.handlers.Callback(inbox.push), allowed_origin=origin)
        )
        return inbox

    # health
    def reject(self, reason: str) -> None:
        with self.counters.lock:
            self.counters.rejected += 1
            self.counters.last_error = reason[:500]
        now = time.monotonic()
        # rate-limited so a flood of bad input cannot flood the log
        if len(self._reject_log_times) < 20 or now - self._reject_log_times[0] > 1.0:
            self._reject_log_times.append(now)
            self.log.warning("rejected input: %s", reason, extra={"fields": {"rejected": self.counters.rejected}})

    def error(self, reason: str) -> None:
        with self.counters.lock:
            self.counters.last_error = reason[:500]
        self.log.error(reason)

    def cycle(self) -> None:
        """Mark one unit of the service's main work (its rate goes in the heartbeat)."""
        now = time.monotonic()
        self._cycle_times.append(now)
        self.counters.cycles += 1

    def rate_hz(self, window_s: float = 2.0) -> float:
        now = time.monotonic()
        recent = [t for t in self._cycle_times if now - t <= window_s]
        span = min(window_s, now - self.started)
        return len(recent) / span if span > 0 else 0.0

    def heartbeat(self) -> None:
        if self._health is None:
            return
        c = self.counters
        with c.lock:
            hb = Heartbeat(
                service=self.name,
                rate_hz=self.rate_hz(),
                received=c.received,
                rejected=c.rejected,
                published=c.published,
                last_error=c.last_error,
                status=c.status,
                counts=dict(c.counts),
                flags=dict(c.flags),
            )
        hb.header.stamp_ns = time.time_ns()
        self._health.put(hb)

    def spin_once(self, sleep_s: float | None = None) -> None:
        """Heartbeat when due, then wait up to `poll_s` (or `sleep_s`); returns at once when input arrives
        or on stop. The caller's loop body must follow (it takes what woke the wait)."""
        now = time.monotonic()
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + 1.0 / self.settings.heartbeat_hz
            self.heartbeat()
        wait_s = self.settings.poll_s if sleep_s is None else max(0.0, sleep_s)
        wait_s = min(wait_s, max(0.0, self._next_heartbeat - now))
        if wait_s > 0.0:
            self._wake.wait(wait_s)
        # cleared after the wait and before the loop looks at its inboxes: an arrival from here on sets it again
        self._wake.clear()
        if self._stop.is_set():
            self._wake.set()
