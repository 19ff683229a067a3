"""Node runtime and safety over real Zenoh sessions on loopback: router and peers, an outside observer,
bad input counted and survived, the egress watchdog and e-stop, settings from YAML + environment."""

from __future__ import annotations

import json
import math
import signal
import time
from pathlib import Path

import pytest
import yaml
import zenoh
from zenoh_helpers import (
    Collector,
    ServiceProcess,
    client,
    endpoint,
    free_port,
    heartbeats,
    matched_publisher,
    router,
    settings,
    wait_for,
)

from schemas import BaseCommand, Command, EStop, Header, State, decode, encode
from services.runtime.node import Node
from services.runtime.node_settings import NodeSettings, ZenohSettings


# ---- node-level tests (in-process sessions) ------------------------------------------------------
def _node(name: str, zenoh_settings: ZenohSettings, robot: str = "r1") -> Node:
    return Node(NodeSettings(service=name, robot=robot, zenoh=zenoh_settings), install_signals=False)


def _exchange(a: Node, b: Node, observer_port: int) -> None:
    with a, b:
        observer = client(observer_port)  # an outside client, joining after the services
        col = Collector(observer)
        pub = a.publisher("cmd")
        sub = b.subscribe("cmd", newest_only=False)
        back = b.publisher("state")
        back_sub = a.subscribe("state")
        got: list[Command] = []
        got_state: list[State] = []

        def step() -> bool:
            pub.put(Command(v_ref=0.5, omega_ref=0.1))
            back.put(State(x=1.0, y=2.0, theta=0.0, v=0.5, omega=0.1))
            a.heartbeat()
            got.extend(sub.drain())
            if (s := back_sub.take()) is not None:
                got_state.append(s)
            return bool(got) and bool(got_state)

        assert wait_for(step, 10.0, step=0.05), "the two nodes did not receive each other's messages"
        assert got[0].v_ref == 0.5 and got_state[0].x == 1.0
        assert got[-1].header.seq > 0 or len(got) == 1

        def seen_all() -> bool:
            pub.put(Command(v_ref=0.5, omega_ref=0.1))
            back.put(State(x=1.0, y=2.0, theta=0.0, v=0.5, omega=0.1))
            a.heartbeat()
            return {"gpmppi/r1/cmd", "gpmppi/r1/state", "gpmppi/r1/health/a"} <= col.keys()

        assert wait_for(seen_all, 5.0, step=0.05), f"the outside client saw only {col.keys()}"
        _, payload, _ = col.on("gpmppi/r1/cmd")[0]
        assert decode(Command, payload).v_ref == 0.5
        alive = {str(r.ok.key_expr) for r in observer.liveliness().get("gpmppi/r1/alive/**") if r.ok is not None}
        assert alive == {"gpmppi/r1/alive/a", "gpmppi/r1/alive/b"}
        observer.close()


def test_two_nodes_through_a_router_and_an_outside_client_sees_every_key() -> None:
    port = free_port()
    with router(port):
        zs = ZenohSettings(mode="client", connect=[endpoint(port)])
        _exchange(_node("a", zs), _node("b", zs), port)


def test_two_nodes_as_listening_peers() -> None:
    pa, pb = free_port(), free_port()
    a = _node("a", ZenohSettings(mode="peer", listen=[endpoint(pa)], connect=[]))
    b = _node("b", ZenohSettings(mode="peer", listen=[endpoint(pb)], connect=[endpoint(pa)]))
    _exchange(a, b, pa)


def test_publisher_sets_json_encoding_and_refuses_non_finite() -> None:
    port = free_port()
    with router(port):
        observer = client(port)
        encodings: list[str] = []
        sub = observer.declare_subscriber("gpmppi/r1/cmd", lambda s: encodings.append(str(s.encoding)))
        node = _node("a", ZenohSettings(mode="client", connect=[endpoint(port)]))
        with node:
            pub = node.publisher("cmd")
            cmd = Command(v_ref=1.0, omega_ref=0.0)
            assert wait_for(lambda: (pub.put(cmd), bool(encodings))[1], 5.0, step=0.05)
            cmd.v_ref = math.nan  # assignment is not validated; the publisher re-validates
            with pytest.raises(ValueError):
                pub.put(cmd)
            with pytest.raises(TypeError):
                pub.put(State(x=0, y=0, theta=0, v=0, omega=0))  # type: ignore[arg-type]
        sub.undeclare()
        observer.close()
        assert encodings[0].startswith("application/json")


def test_settings_yaml_then_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from services.egress import Settings as EgressSettings

    path = tmp_path / "egress.yaml"
    path.write_text(
        yaml.safe_dump({"robot": "r9", "watchdog_timeout_s": 0.3, "zenoh": {"connect": ["tcp/127.0.0.1:1"]}})
    )
    s = EgressSettings.load(path)
    assert (s.robot, s.watchdog_timeout_s, s.zenoh.connect, s.rate_hz) == ("r9", 0.3, ["tcp/127.0.0.1:1"], 20.0)
    monkeypatch.setenv("GPMPPI_WATCHDOG_TIMEOUT_S", "0.7")
    monkeypatch.setenv("GPMPPI_ZENOH__MODE", "peer")
    s = EgressSettings.load(path)
    assert s.watchdog_timeout_s == 0.7 and s.zenoh.mode == "peer" and s.robot == "r9"
    monkeypatch.delenv("GPMPPI_WATCHDOG_TIMEOUT_S")
    path.write_text(yaml.safe_dump({"watchdog_timeout_s": -1}))
    with pytest.raises(ValueError, match="watchdog_timeout_s"):
        EgressSettings.load(path)
    with pytest.raises(FileNotFoundError):
        EgressSettings.load(tmp_path / "missing.yaml")
    for name, f in EgressSettings.model_fields.items():
        assert f.description, f"setting {name} has no description"


# ---- services in their own processes -------------------------------------------------------------
def _bad_payloads() -> list[tuple[str, bytes]]:
    good = json.loads(encode(Command(v_ref=0.3, omega_ref=0.0)))
    wrong_version = {**good, "header": {**good["header"], "schema_version": 99}}
    return [
        ("invalid json", b"{not json"),
        ("wrong type", json.dumps({**good, "v_ref": "fast"}).encode()),
        ("NaN", json.dumps({**good, "v_ref": float("nan")}).encode()),  # json.dumps writes NaN
        ("infinity", b'{"v_ref": Infinity, "omega_ref": 0.0}'),
        ("wrong schema_version", json.dumps(wrong_version).encode()),
        ("oversized", b'{"v_ref": 1.0, "omega_ref": 0.0, "pad": "' + b"x" * (5 * 1024 * 1024) + b'"}'),
        ("missing field", b'{"v_ref": 1.0}'),
    ]


def test_egress_survives_bad_input_and_never_publishes_non_finite(tmp_path: Path) -> None:
    port = free_port()
    with router(port):
        observer = client(port)
        col = Collector(observer)
        egress = ServiceProcess("egress", settings("egress", port, rate_hz=20.0), tmp_path)
        try:
            assert wait_for(lambda: bool(heartbeats(col, "r1", "egress")), 15.0), egress.log()
            pub = matched_publisher(observer, "gpmppi/r1/cmd", congestion_control=zenoh.CongestionControl.BLOCK)
            # one at a time, each logged before the next is sent, so a failure names the payload (one that replaced
            # another in egress's newest-only inbox is counted too, on arrival: `services.runtime.scheduling.Inbox`)
            for i, (what, payload) in enumerate(_bad_payloads()):
                pub.put(payload)
                logged = wait_for(lambda n=i: egress.log().count("rejected input") > n, 10.0)
                assert logged, (what, egress.log()[-3000:])
            n_bad = len(_bad_payloads())
            # 15 s: the count arrives with a heartbeat, and on a loaded machine the last of them took over 5 s once
            counted = wait_for(lambda: any(h.rejected >= n_bad for h in heartbeats(col, "r1", "egress")), 15.0)
            assert counted, (n_bad, heartbeats(col, "r1", "egress")[-1:], egress.log()[-3000:])
            # still alive and obeying valid commands
            for _ in range(10):
                pub.put(encode(Command(v_ref=0.4, omega_ref=0.2, header=Header(stamp_ns=time.time_ns()))))
                time.sleep(0.05)
            assert egress.alive()
            base = [decode(BaseCommand, p) for _, p, _ in col.on("gpmppi/r1/base/cmd")]
            assert base and all(math.isfinite(b.v) and math.isfinite(b.omega) for b in base)
            assert any(b.reason == "planner" and abs(b.v - 0.4) < 1e-9 and abs(b.omega - 0.2) < 1e-9 for b in base)
            hb = heartbeats(col, "r1", "egress")[-1]
            assert hb.rejected >= n_bad and hb.last_error
        finally:
            assert egress.stop() == 0
            observer.close()
    log = egress.log()
    assert log.count("rejected input") >= 5 and "schema_version" in log and "exceeds" in log


@pytest.mark.exclusive  # alone: its windows are fixed offsets at the observer (0.45 s after the last command)
def test_egress_watchdog_limits_and_estop(tmp_path: Path) -> None:
    port = free_port()
    with router(port):
        observer = client(port)
        col = Collector(observer)
        cfg = settings("egress", port, rate_hz=20.0, watchdog_timeout_s=0.3, accel_limit=2.0, v_limits=[0.0, 1.0])
        egress = ServiceProcess("egress", cfg, tmp_path)
        try:
            assert wait_for(lambda: bool(heartbeats(col, "r1", "egress")), 15.0), egress.log()
            cmd_pub = matched_publisher(observer, "gpmppi/r1/cmd")
            estop_pub = matched_publisher(observer, "gpmppi/r1/estop")
            t_cmd = time.monotonic()
            for _ in range(20):  # 1 s of commands above the velocity limit
                cmd_pub.put(encode(Command(v_ref=5.0, omega_ref=0.0, header=Header(stamp_ns=time.time_ns()))))
                time.sleep(0.05)
            t_stop = time.monotonic()
            time.sleep(1.0)
            base = [(t, decode(BaseCommand, p)) for t, p, _ in col.on("gpmppi/r1/base/cmd")]
            during = [b for t, b in base if t_cmd < t < t_stop]
            assert max(b.v for b in during) == pytest.approx(1.0)  # velocity limit
            ramp = [b.v for b in during[:5]]
            assert ramp[0] < 0.5 and all(b2 >= b1 for b1, b2 in zip(ramp, ramp[1:], strict=False))  # accel limit
            after = [b for t, b in base if t > t_stop + 0.3 + 0.15]
            assert len(after) >= 5, "the watchdog must keep sending at a steady rate"
            assert all(b.v == 0.0 and b.omega == 0.0 and b.reason == "watchdog" for b in after)
            # e-stop: zero while engaged even with fresh commands, planner again once released
            estop_pub.put(encode(EStop(engaged=True, reason="test")))
            time.sleep(0.2)
            t_e = time.monotonic()
            for _ in range(10):
                cmd_pub.put(encode(Command(v_ref=0.5, omega_ref=0.0, header=Header(stamp_ns=time.time_ns()))))
                time.sleep(0.05)
            estop_pub.put(encode(EStop(engaged=False)))
            time.sleep(0.1)
            for _ in range(10):
                cmd_pub.put(encode(Command(v_ref=0.5, omega_ref=0.0, header=Header(stamp_ns=time.time_ns()))))
                time.sleep(0.05)
            base = [(t, decode(BaseCommand, p)) for t, p, _ in col.on("gpmppi/r1/base/cmd")]
            engaged = [b for t, b in base if t_e < t < t_e + 0.45]
            assert engaged and all(b.v == 0.0 and b.reason == "estop" for b in engaged)
            assert base[-1][1].reason in ("planner", "limit") and base[-1][1].v > 0.0
        finally:
            assert egress.stop() == 0
            observer.close()


def test_a_service_prints_its_threads_stacks_on_sigusr1_and_runs_on(tmp_path: Path) -> None:
    """`kill -USR1 PID`: where a service that does not stop, or stops answering, is stuck (faulthandler)."""
    port = free_port()
    with router(port):
        observer = client(port)
        col = Collector(observer)
        egress = ServiceProcess("egress", settings("egress", port, rate_hz=20.0, heartbeat_hz=5.0), tmp_path)
        try:
            assert wait_for(lambda: bool(heartbeats(col, "r1", "egress")), 15.0), egress.log()
            egress.process.send_signal(signal.SIGUSR1)
            # the main thread's frames, down to the service's entry point (the dump is written as it is read)
            dumped = wait_for(lambda: "Current thread" in (log := egress.log()) and "services/run.py" in log, 10.0)
            assert dumped and "services/runtime/node.py" in egress.log(), egress.log()[-3000:]
            beats = len(heartbeats(col, "r1", "egress"))
            assert wait_for(lambda: len(heartbeats(col, "r1", "egress")) > beats + 2, 10.0)  # it runs on
        finally:
            assert egress.stop() == 0
            observer.close()
