"""A Zenoh router in its own process (what the launcher starts; `zenohd` can replace it).

Services connect to it as clients; anyone who connects to it sees every key.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path

import zenoh
from pydantic import Field

from services.runtime.logs import setup_logging
from services.runtime.node_settings import DEFAULT_ROUTER, NodeSettings
from services.runtime.signals import StopSignals

log = logging.getLogger("gpmppi.router")


class RouterSettings(NodeSettings):
    service: str = Field("router", description="name in logs")
    listen: list[str] = Field(default_factory=lambda: [DEFAULT_ROUTER], description="endpoints the router listens on")
    router_config_file: str | None = Field(None, description="a Zenoh json5 router config applied first")


def router_config(settings: RouterSettings) -> zenoh.Config:
    config = zenoh.Config.from_file(settings.router_config_file) if settings.router_config_file else zenoh.Config()
    config.insert_json5("mode", json.dumps("router"))
    config.insert_json5("listen/endpoints", json.dumps(settings.listen))
    config.insert_json5("connect/endpoints", json.dumps([]))
    config.insert_json5("scouting/multicast/enabled", json.dumps(settings.zenoh.multicast_scouting))
    return config


def run(settings: RouterSettings) -> int:
    stop = threading.Event()
    StopSignals(lambda signum: stop.set())  # for the process's life: the router stops on SIGINT / SIGTERM
    session = zenoh.open(router_config(settings))
    log.info("router listening on %s", ", ".join(settings.listen), extra={"fields": {"zid": str(session.zid())}})
    try:
        stop.wait()
    finally:
        t0 = time.monotonic()
        session.close()
        log.info("router closed in %.3f s", time.monotonic() - t0)
    return 0


def main(config: str | Path | None = None) -> int:
    settings = RouterSettings.load(config)
    setup_logging(settings.service, settings.log_level, settings.log_json)
    return run(settings)
