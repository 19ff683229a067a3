"""One process of a service at a time: its liveliness token (`LIVELINESS_PREFIX`) says at the router whether
another is alive. A process that takes over waits until its predecessor's token is gone (`wait_while_alive`); one
started to stand by (`GPMPPI_STANDBY`, systemd) keeps what the live one publishes on the keys it would resume from
and waits for its token's deletion (`stand_by`). `services.runtime.node.Node.open` calls them."""

from __future__ import annotations

import logging
import threading
import time

import zenoh

from services.runtime.role import HANDOVER
from services.runtime.session import StoppedWhileWaiting

LIVELINESS_PREFIX = "gpmppi/{robot}/alive/{service}"


def alive(session: zenoh.Session, key: str) -> bool:
    """Whether a liveliness token on `key` (another process of this service) is alive at the router."""
    replies = session.liveliness().get(key, timeout=1.0)
    return any(reply.ok is not None for reply in replies)


def wait_while_alive(session: zenoh.Session, key: str, service: str, log: logging.Logger,
                     stop: threading.Event) -> None:
    """Wait until no other process of this service holds its liveliness token (a predecessor whose death the
    router has not seen yet, or one that is alive elsewhere), before declaring ours and publishing."""
    if not alive(session, key):
        return
    t0 = time.monotonic()
    log.warning("another %s is alive (%s); waiting until it is gone", service, key)
    while alive(session, key):
        if stop.wait(0.02):
            raise StoppedWhileWaiting(f"stopped while another {service} was alive")
    waited = round(time.monotonic() - t0, 3)
    log.info("the other %s is gone", service, extra={"fields": {"waited_s": waited}})


def stand_by(session: zenoh.Session, key: str, robot: str, service: str, log: logging.Logger,
             stop: threading.Event, wake: threading.Event) -> dict[str, bytes]:
    """`GPMPPI_STANDBY` (systemd): while another process of this service is alive, keep the last payload on the
    keys it would resume from and wait, woken by its liveliness token's deletion (no polling); what was kept
    (registered key name -> payload: the node's `handover`)."""
    last: dict[str, bytes] = {}
    subs = [
        session.declare_subscriber(
            f"gpmppi/{robot}/{suffix}",
            lambda sample, n=name: last.__setitem__(n, sample.payload.to_bytes()),
        )
        for name, suffix in HANDOVER.get(service, {}).items()
    ]
    # a token's change (and a stop) ends the wait at once
    watch = session.liveliness().declare_subscriber(key, lambda sample: wake.set())
    try:
        if alive(session, key):
            t0 = time.monotonic()
            log.info("standing by: another %s is alive (%s)", service, key)
            while alive(session, key):
                wake.wait(5.0)
                wake.clear()
                if stop.is_set():
                    raise StoppedWhileWaiting(f"stopped while standing by for {service}")
            log.warning("taking over: the other %s is gone", service,
                        extra={"fields": {"stood_by_s": round(time.monotonic() - t0, 1)}})
    finally:
        watch.undeclare()
        for sub in subs:
            sub.undeclare()
    return dict(last)
