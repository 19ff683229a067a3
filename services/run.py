"""Run one service: `python -m services.run NAME [--config FILE.yaml]` (what `gpmppi service` calls).

Every service module defines `Settings` (a `NodeSettings`) and `run(settings) -> int` (exit code).
"""

from __future__ import annotations

import argparse
import faulthandler
import importlib
import logging
import signal
import sys
from pathlib import Path
from types import ModuleType

from pydantic import ValidationError

from services.runtime.node import setup_logging
from services.runtime.scheduling import apply_process_settings

SERVICES: dict[str, str] = {
    "router": "services.router",
    "sim": "services.sim",
    "ingress": "services.ingress",
    "terrain": "services.terrain",
    "planner": "services.planner",
    "egress": "services.egress",
    "recorder": "services.recorder",
    "viewer": "services.viewer",
}


def service_module(kind: str) -> ModuleType:
    if kind not in SERVICES:
        raise KeyError(f"unknown service {kind!r}; known: {', '.join(SERVICES)}")
    return importlib.import_module(SERVICES[kind])


def settings_class(kind: str) -> type:
    module = service_module(kind)
    return module.RouterSettings if kind == "router" else module.Settings


def run_service(kind: str, config: str | Path | None = None) -> int:
    module = service_module(kind)
    try:
        settings = settings_class(kind).load(config)
    except (ValidationError, FileNotFoundError) as exc:
        print(f"gpmppi service {kind}: bad configuration ({config}): {exc}", file=sys.stderr)
        return 2
    setup_logging(settings.service, settings.log_level, settings.log_json)
    # `kill -USR1 PID` prints every thread's stack to stderr (the service's log) and the service runs on: where a
    # service that does not stop, or stops answering, is stuck
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    try:
        apply_process_settings(settings)
        return int(module.run(settings) or 0)
    except KeyboardInterrupt:
        # SIGINT before the service's node took over the signal (e.g. while the planner compiles)
        return 0
    except Exception:
        logging.getLogger(f"gpmppi.{settings.service}").exception("service failed")
        return 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.run", description="Run one gpmppi service.")
    parser.add_argument("name", choices=sorted(SERVICES))
    parser.add_argument("--config", type=Path, default=None, help="YAML settings file")
    args = parser.parse_args(argv)
    return run_service(args.name, args.config)


if __name__ == "__main__":
    sys.exit(main())
