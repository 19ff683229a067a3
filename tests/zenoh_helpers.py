"""Zenoh test helpers shared by the service, ROS 2, recorder and launch tests: free loopback ports, a
router-mode session, clients, a collector of everything under a key, and a service run as its own process."""

from __future__ import annotations

import itertools
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import yaml
import zenoh

from schemas import BaseCommand, Heartbeat, State, decode, encode
from services.runtime.node_settings import ZenohSettings

REPO = Path(__file__).resolve().parents[1]


# Ports the tests listen on: below the OS's ephemeral range (32768-60999 on Linux), which it hands to every outgoing
# connection, the tests' own Zenoh clients included; a port the OS had just reported free (bind to port 0) could be
# taken by one of those before the test's router bound it ("Address already in use", seen on three workers). Each
# pytest-xdist worker has a slice of its own, and takes its ports in turn from a start that differs per process.
_PORT_BASE = 20000
_PORT_SLICE = 1500
_WORKER = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
_next_port = itertools.count(os.getpid() % _PORT_SLICE)


def free_port() -> int:
    """A loopback TCP port free now that no other worker of this run is given (tried by binding it)."""
    first = _PORT_BASE + _PORT_SLICE * (_WORKER % 8)
    for _ in range(_PORT_SLICE):
        port = first + next(_next_port) % _PORT_SLICE
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue  # in use (another run, a socket still closing): the next one
            return port
    raise RuntimeError(f"no free loopback port in {first}-{first + _PORT_SLICE - 1}")


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


@contextmanager
def router(port: int) -> Iterator[zenoh.Session]:
    config = zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("listen/endpoints", json.dumps([endpoint(port)]))
    config.insert_json5("scouting/multicast/enabled", "false")
    # a router's open waits `scouting/delay` (500 ms by default) for peers to scout; with multicast off there are
    # none, so that wait was half a second of wall time for every test that opens a router (38 in `-m "not slow"`)
    config.insert_json5("scouting/delay", "0")
    session = zenoh.open(config)
    try:
        yield session
    finally:
        session.close()


def client(port: int) -> zenoh.Session:
    return zenoh.open(ZenohSettings(mode="client", connect=[endpoint(port)]).to_config())


def matched_publisher(session: zenoh.Session, key: str, **kwargs) -> zenoh.Publisher:
    """A publisher that already has a matching subscriber (so the first put is not lost to routing)."""
    pub = session.declare_publisher(key, **kwargs)
    assert wait_for(lambda: pub.matching_status.matching, 15.0), f"no subscriber for {key}"
    return pub


def put_state_and_base_command(
    state_pub: zenoh.Publisher, cmd_pub: zenoh.Publisher, x, u, stamp_ns: int
) -> None:
    """Publish the state `x` (x, y, theta, v, omega) and the base command `u` (v, omega) applied from it, both stamped
    `stamp_ns` (how ingress and egress pair them for the terrain service)."""
    state = State(x=x[0], y=x[1], theta=x[2], v=x[3], omega=x[4])
    state.header.stamp_ns = stamp_ns
    state_pub.put(encode(state))
    cmd = BaseCommand(v=u[0], omega=u[1])
    cmd.header.stamp_ns = stamp_ns
    cmd_pub.put(encode(cmd))


def wait_for(predicate: Callable[[], bool], timeout: float, step: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return predicate()


class Collector:
    """An outside observer: every sample on a key expression, with arrival times."""

    def __init__(self, session: zenoh.Session, key_expr: str = "gpmppi/**") -> None:
        self.samples: list[tuple[float, str, bytes, bytes | None]] = []
        self.lock = threading.Lock()
        self._sub = session.declare_subscriber(key_expr, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        with self.lock:
            self.samples.append((time.monotonic(), str(sample.key_expr), sample.payload.to_bytes(), att))

    def on(self, key: str) -> list[tuple[float, bytes, bytes | None]]:
        with self.lock:
            return [(t, p, a) for t, k, p, a in self.samples if k == key]

    def keys(self) -> set[str]:
        with self.lock:
            return {k for _, k, _, _ in self.samples}


class ServiceProcess:
    """A service in its own process, as the launcher runs it."""

    def __init__(self, kind: str, config: dict, tmp_path: Path) -> None:
        path = tmp_path / f"{kind}-{config.get('service', kind)}.yaml"
        path.write_text(yaml.safe_dump(config))
        env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
        self.log_path = tmp_path / f"{kind}.log"
        self._log = open(self.log_path, "wb")  # noqa: SIM115 - closed in stop()
        self.process = subprocess.Popen(
            [sys.executable, "-m", "services.run", kind, "--config", str(path)],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env=env,
            cwd=tmp_path,
        )

    def alive(self) -> bool:
        return self.process.poll() is None

    def stop(self, timeout: float = 10.0) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                # where it is stuck: every thread's stack (services.run registers SIGUSR1 with faulthandler)
                self.process.send_signal(signal.SIGUSR1)
                time.sleep(2.0)
                self.process.kill()
                self.process.wait()
                self._log.close()
                raise AssertionError(
                    f"service did not exit within {timeout} s of SIGINT; its log's end:\n{self.log()[-6000:]}"
                ) from None
        self._log.close()
        return self.process.returncode

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


def heartbeats(col: Collector, robot: str, service: str) -> list[Heartbeat]:
    return [decode(Heartbeat, p) for _, p, _ in col.on(f"gpmppi/{robot}/health/{service}")]


def settings(service: str, port: int, robot: str = "r1", **extra) -> dict:
    return {"service": service, "robot": robot, "zenoh": {"mode": "client", "connect": [endpoint(port)]}, **extra}


def without_spares(launch):  # noqa: ANN001, ANN201 - services.launch.launch_file.LaunchFile (imported by its callers)
    """`run_launch(..., edit=without_spares)`: the launch file with no warm spares. For tests of something else than
    the spares (tests/test_faults.py has theirs): each spare is a process that loads everything, so a 20 s stack
    costs a third more CPU with them (18.5 against 12.2 CPU seconds, `gpmppi launch --duration 20`), which a 2-core
    machine running the suite pays in wall time."""
    return launch.model_copy(update={"spares": []})
