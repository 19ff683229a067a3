"""Run one service: `python -m services.run NAME [--config FILE.yaml]` (what `gpmppi service` calls).

Every service module defines `Settings` (a `NodeSettings`) and `run(settings) -> int` (exit code).
"""

from __future__ import annotations

import argparse
import faulthandler
import importlib
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from types import ModuleType

# Only the standard library at the top: `main` arms `follow_launcher` first, before the imports of a service
# (pydantic, numpy, zenoh, ...: 0.4 s on an idle machine, seconds on a loaded one), so a child started just before
# its launcher dies does not outlive it by its imports (imported in `run_service`)

SERVICES: dict[str, str] = {
    "router": "services.router",
    "sim": "services.sim",
    "ingress": "services.ingress",
    "terrain": "services.terrain",
    "planner": "services.planner",
    "egress": "services.egress",
    "nav": "services.nav",
    "recorder": "services.recorder",
    "viewer": "services.viewer",
    "foxglove": "services.foxglove",
    "calibrate": "services.calibrate",
}


SETTINGS_CHANGED_EXIT = 3  # a spare's settings changed before it took over: it exits, the service restarts

# set by the launcher in each child's environment: the launcher's pid (services.launch.supervisor)
LAUNCHER_PID_ENV = "GPMPPI_LAUNCHER_PID"
PR_SET_PDEATHSIG = 1  # linux/prctl.h


def follow_launcher() -> None:
    """A service started by a launcher stops when that launcher dies, however it dies (SIGKILL included), so no
    service runs on as an orphan, driving the robot with no one supervising it.

    Linux: the kernel sends this process SIGTERM (its graceful stop) when the launcher dies (PR_SET_PDEATHSIG);
    if the launcher died before that was set, the parent is no longer the launcher and the process exits at
    once. Elsewhere a thread checks the parent twice a second. Nothing happens without `GPMPPI_LAUNCHER_PID`
    (a service run by hand, or by systemd)."""
    launcher = os.environ.get(LAUNCHER_PID_ENV)
    if not launcher or not launcher.isdigit():
        return
    launcher_pid = int(launcher)
    if sys.platform.startswith("linux"):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) != 0:
            print(f"services.run: prctl(PR_SET_PDEATHSIG) failed: errno {ctypes.get_errno()}", file=sys.stderr)
    if os.getppid() != launcher_pid:
        print(f"services.run: the launcher (pid {launcher_pid}) is gone; not starting", file=sys.stderr)
        os._exit(0)
    if not sys.platform.startswith("linux"):

        def watch() -> None:
            while os.getppid() == launcher_pid:
                time.sleep(0.5)
            os.kill(os.getpid(), signal.SIGTERM)

        threading.Thread(target=watch, name="launcher-watch", daemon=True).start()


def service_module(kind: str) -> ModuleType:
    if kind not in SERVICES:
        raise KeyError(f"unknown service {kind!r}; known: {', '.join(SERVICES)}")
    return importlib.import_module(SERVICES[kind])


def settings_class(kind: str) -> type:
    module = service_module(kind)
    return module.RouterSettings if kind == "router" else module.Settings


def run_service(kind: str, config: str | Path | None = None) -> int:
    from pydantic import ValidationError

    from services.runtime.logs import setup_logging
    from services.runtime.node import SettingsChanged
    from services.runtime.scheduling import apply_process_settings

    module = service_module(kind)
    try:
        settings = settings_class(kind).load(config)
    except (ValidationError, FileNotFoundError, ValueError) as exc:
        # a ConfigFileError is one line, FILE:LINE:COL: problem
        print(f"gpmppi service {kind}: bad configuration: {exc}", file=sys.stderr)
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
    except SettingsChanged as exc:
        logging.getLogger(f"gpmppi.{settings.service}").error("%s", exc)
        return SETTINGS_CHANGED_EXIT
    except Exception:
        logging.getLogger(f"gpmppi.{settings.service}").exception("service failed")
        return 1


def main(argv: list[str] | None = None) -> int:
    follow_launcher()
    # a warm spare's start (its imports first) at a lower CPU priority than the services it backs; its go takes
    # the priority back (services.runtime.spare_priority)
    from services.runtime.spare_priority import lower_for_standby

    lower_for_standby()
    parser = argparse.ArgumentParser(prog="python -m services.run", description="Run one gpmppi service.")
    parser.add_argument("name", choices=sorted(SERVICES))
    parser.add_argument("--config", type=Path, default=None, help="YAML settings file")
    args = parser.parse_args(argv)
    return run_service(args.name, args.config)


def exit_now(code: int) -> None:
    """Leave once the service has stopped (its session closed, its files finished), without the interpreter's
    teardown: freeing every module's objects one by one and joining leftover threads took 0.1-0.6 s on an idle
    machine after the session had closed in 3 ms (the terrain service, with cvxpy, the longest), and seconds on a
    loaded one, which is how long a service outlived a launcher that died. The output is flushed first."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # the launcher that read it is gone, or it is closed
            pass
    os._exit(code)


if __name__ == "__main__":
    exit_now(main())
