"""Opening a service's Zenoh session: a client whose router is not up yet waits for it (services start in any
order, as under systemd), with Zenoh's own connect retry and one log line while it waits."""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

import zenoh

if TYPE_CHECKING:
    from services.runtime.node_settings import ZenohSettings


class StoppedWhileWaiting(KeyboardInterrupt):
    """Stopped (SIGINT/SIGTERM) while waiting for the router: a clean exit, not a failure."""


def _accepts_tcp(endpoint: str) -> bool:
    """Whether a tcp/ or tls/ endpoint accepts a TCP connection (something listens there)."""
    import socket

    proto, _, address = endpoint.partition("/")
    if proto not in ("tcp", "tls") or ":" not in address:
        return False
    host, port = address.split("#")[0].split("?")[0].rsplit(":", 1)
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=0.5):
            return True
    except (OSError, ValueError):
        return False


def open_session(
    settings: ZenohSettings, log: logging.Logger, stop: threading.Event | None = None, attempt_ms: int = 500
) -> zenoh.Session:
    """Open a Zenoh session; a client whose router is not up yet waits for it (Zenoh's own connect retry, with
    backoff, in attempts of `attempt_ms` between which `stop` is checked) and logs one line while it waits.

    Raises `StoppedWhileWaiting` when `stop` is set meanwhile, and `zenoh.ZError` when `wait_for_router_s`
    passes, or when the endpoint accepts connections but keeps refusing the session (credentials, TLS)."""
    if settings.mode != "client":
        return zenoh.open(settings.to_config())
    try:
        return zenoh.open(settings.to_config(connect_timeout_ms=0))
    except zenoh.ZError as exc:
        first_error = exc
    endpoints = ", ".join(settings.connect)
    if settings.wait_for_router_s == 0:
        raise zenoh.ZError(f"no Zenoh router at {endpoints}: {str(first_error).split(' at ')[0]}")
    log.warning(f"waiting for router at {endpoints}", extra={"fields": {"error": str(first_error).split(" at ")[0]}})
    t0 = time.monotonic()
    refused = 0
    while True:
        if stop is not None and stop.is_set():
            raise StoppedWhileWaiting(f"stopped while waiting for the router at {endpoints}")
        waited = time.monotonic() - t0
        limit = settings.wait_for_router_s
        if limit is not None and waited >= limit:
            raise zenoh.ZError(f"no Zenoh router at {endpoints} after {waited:.1f} s: start the router first")
        chunk = attempt_ms if limit is None else max(1, min(attempt_ms, int((limit - waited) * 1000)))
        try:
            session = zenoh.open(settings.to_config(connect_timeout_ms=chunk))
        except zenoh.ZError as exc:
            # something listens but the session is refused, attempt after attempt: waiting will not help
            refused = refused + 1 if any(_accepts_tcp(e) for e in settings.connect) else 0
            if refused >= 3:
                raise zenoh.ZError(
                    f"the router at {endpoints} accepts connections but refuses this session ({exc}): check the "
                    "credentials / TLS settings of this service and of the router"
                ) from exc
            continue
        log.info(f"router reached at {endpoints}", extra={"fields": {"waited_s": round(time.monotonic() - t0, 2)}})
        return session
