"""Property-based fuzzing of every service over a real Zenoh session on loopback: hypothesis payloads (junk,
model-shaped dicts with NaN / inf / wrong types / wrong schema versions, huge arrays, deep nesting, other
encodings, valid-but-extreme messages) on every key each service subscribes to.

Every service runs as its own process in its own robot namespace (so each one's counters count only what this
test sent it); the recorder and the viewer subscribe to everything and see all of it. Pass criteria:
- no crash: every process is alive after the fuzz, still does its work on valid input, and exits 0 on SIGINT;
- rejections counted: each payload is sent only once the service has taken the previous one (its heartbeat's
  `received` went up), so newest-only inboxes overwrite nothing; every payload that `schemas.decode` refuses
  is counted in `rejected`;
- no non-finite output: every sample any service published decodes strictly (finite; egress within limits);
- no exception escapes a callback: no traceback in any service's log; the recorder wrote every payload sent.

Bounded and deterministic: a fixed number of examples per key, derandomized, no example database."""

from __future__ import annotations

import hashlib
import os
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import zenoh
from fuzz_strategies import extreme_tasks, floats, junk, materialize, payloads, valid_state
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from zenoh_helpers import ServiceProcess, client, free_port, router, wait_for
from zenoh_helpers import settings as service_settings

from schemas import (
    BaseCommand,
    Command,
    DecodeError,
    EStop,
    Heartbeat,
    Message,
    State,
    Task,
    TerrainWeights,
    decode,
    encode,
    key_for,
    model_for_key,
)
from services.codec import ros2

pytestmark = pytest.mark.slow  # eight service processes: ~1 min (they still run in CI)

EXAMPLES = 25  # per key: ~10 keys, each example waits for the service to take it
# no shrinking: a failing example is reported as it was sent (replaying it against a process that has changed
# state, or died, proves nothing)
FUZZ = settings(
    max_examples=EXAMPLES, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck),
    phases=[Phase.explicit, Phase.generate],
)
ENCODINGS = ["application/json", "application/cdr", "text/plain", "zenoh/bytes", "application/octet-stream"]
HEARTBEAT_HZ = 25.0
ROS2_KEY = ros2.topic_key("odom", "nav_msgs/msg/Odometry")


def _digest(data: bytes) -> bytes:
    return hashlib.blake2b(data, digest_size=16).digest()


class Watch:
    """The test's own view: the newest heartbeat of each (robot, service), and every sample, with arrival times."""

    def __init__(self, session: zenoh.Session) -> None:
        self.lock = threading.Lock()
        self.heartbeat: dict[tuple[str, str], Heartbeat] = {}
        self.samples: list[tuple[float, str, bytes]] = []
        self._sub = session.declare_subscriber("gpmppi/**", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        key, data = str(sample.key_expr), sample.payload.to_bytes()
        with self.lock:
            self.samples.append((time.monotonic(), key, data))
        parts = key.split("/")
        if len(parts) == 4 and parts[2] == "health":
            try:
                hb = decode(Heartbeat, data)
            except DecodeError:
                return
            with self.lock:
                self.heartbeat[(parts[1], parts[3])] = hb

    def hb(self, robot: str, service: str) -> Heartbeat | None:
        with self.lock:
            return self.heartbeat.get((robot, service))

    def on(self, key: str, since: float = 0.0) -> list[bytes]:
        with self.lock:
            return [d for t, k, d in self.samples if k == key and t >= since]


@dataclass
class Target:
    """One service under fuzz: its process, robot namespace and what was sent to it."""

    kind: str
    robot: str
    process: ServiceProcess
    sent: list[bytes] = field(default_factory=list)
    must_reject: int = 0  # sent payloads that schemas.decode refuses


@dataclass
class Stack:
    port: int
    session: zenoh.Session
    watch: Watch
    targets: dict[str, Target]
    record: Path
    sent_by_key: dict[str, list[bytes]] = field(default_factory=dict)


SERVICES = {
    # name: (kind, robot namespace, extra settings)
    "ingress": ("ingress", "f_ingress", {"source": "sim"}),
    "ingress_ros2": ("ingress", "f_ros2", {"source": "ros2", "max_age_s": 1.0}),
    "terrain": ("terrain", "f_terrain", {}),
    "planner": ("planner", "f_planner", {}),
    "egress": ("egress", "f_egress", {}),
    "sim": ("sim", "f_sim", {}),
}


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    port = free_port()
    root = tmp_path_factory.mktemp("fuzz")
    record = root / "fuzz.mcap"
    with router(port):
        session = client(port)
        watch = Watch(session)
        targets: dict[str, Target] = {}
        every = {"key_expr": "gpmppi/**"}
        observers = {
            "recorder": ("recorder", "f_all", {**every, "path": str(record), "flush_interval_s": 0.2}),
            "viewer": ("viewer", "f_all", {**every, "mode": "save", "path": str(root / "fuzz.rrd")}),
        }
        try:
            for name, (kind, robot, extra) in {**observers, **SERVICES}.items():
                cfg = service_settings(kind, port, robot=robot, heartbeat_hz=HEARTBEAT_HZ, **extra)
                (root / name).mkdir()
                targets[name] = Target(kind, robot, ServiceProcess(kind, cfg, root / name))
            for name, t in targets.items():
                # the planner compiles its kernels on a cold cache (minutes); warm, all are up in seconds
                up = wait_for(lambda t=t: watch.hb(t.robot, t.kind) is not None or not t.process.alive(), 600.0, 0.1)
                assert up and t.process.alive(), f"{name} did not come up:\n{t.process.log()[-3000:]}"
            yield Stack(port, session, watch, targets, record)
        finally:
            codes = {name: t.process.stop() for name, t in reversed(targets.items())}
            session.close()
        assert all(c == 0 for c in codes.values()), codes


def send(stack: Stack, name: str, key_name: str | None, payload: bytes | dict, encoding: str,
         key: str | None = None) -> None:
    """Send one payload to a service and wait until it has taken it (its heartbeat's `received` went up)."""
    t = stack.targets[name]
    key = key or key_for(key_name, robot=t.robot)
    data = materialize(payload) if not isinstance(payload, tuple) else ros2.odometry_cdr(
        np.array(payload[1]), time.time_ns()
    )
    before = stack.watch.hb(t.robot, t.kind)
    assert before is not None
    t0 = time.monotonic()
    stack.session.put(key, data, encoding=zenoh.Encoding(encoding))
    t.sent.append(data)
    stack.sent_by_key.setdefault(key, []).append(data)
    if key_name is not None:
        try:
            decode(model_for_key(key), data)
        except DecodeError:
            t.must_reject += 1
    took = wait_for(lambda: not t.process.alive() or ((h := stack.watch.hb(t.robot, t.kind)) is not None
                                                      and h.received > before.received), 60.0, 0.005)
    if os.environ.get("GPMPPI_FUZZ_TIMES"):
        print(f"{name} {key} {time.monotonic() - t0:.3f} s {data[:60]!r}")
    assert t.process.alive(), f"{name} died on {data[:300]!r}:\n{t.process.log()[-3000:]}"
    assert took, f"{name} did not take {data[:300]!r} within 60 s:\n{t.process.log()[-2000:]}"


def fuzz_key(stack: Stack, name: str, key_name: str | None, strategy: st.SearchStrategy, key: str | None = None
             ) -> None:
    @FUZZ
    @given(payload=strategy, encoding=st.sampled_from(ENCODINGS))
    def run(payload: bytes | dict, encoding: str) -> None:
        send(stack, name, key_name, payload, encoding, key)

    run()


plain = st.floats(-3.0, 3.0)
cdr_inputs = st.one_of(
    st.binary(max_size=600),
    st.tuples(st.just("odom"), st.lists(floats, min_size=5, max_size=5)),  # fresh, extreme values
    st.integers(0, 700).map(lambda n: ros2.odometry_cdr(np.zeros(5), time.time_ns())[:n]),  # truncated
)
commands = st.builds(lambda v, w: {"header": {"stamp_ns": "__now__"}, "v_ref": v, "omega_ref": w}, floats, floats)
base_commands = st.builds(lambda v, w, r: {"header": {"stamp_ns": "__now__"}, "v": v, "omega": w, "reason": r},
                          floats, floats, st.sampled_from(["planner", "watchdog", "limit", "other"]))

# the planner's input is ingress's output, which refuses |v| > 10 m/s and |omega| > 20 rad/s; but within those
# limits (v = -5 m/s with omega = 20 rad/s at the lane's start), and for 1e6 / 1e308 values, the planner publishes
# a non-finite Plan and dies (DecodeError out of services/planner.py run(); test_fuzz_decode has it as a strict
# xfail, docs/fuzz-soak.md the details). Until that is fixed the states here stay where a Jackal can be: within
# 20 m of the lane, v in [-1, 3] m/s, |omega| <= 4 rad/s
def _within(limit: float) -> st.SearchStrategy[float]:
    return st.one_of(st.sampled_from([0.0, -0.0, 1e-300, limit, -limit]), st.floats(-limit, limit))


plausible_states = st.builds(
    lambda x, y, th, v, w: {"header": {"stamp_ns": "__now__"}, "x": x, "y": y, "theta": th, "v": v, "omega": w},
    _within(20.0), _within(20.0), _within(1e3),
    st.one_of(st.sampled_from([-1.0, 0.0, 3.0]), st.floats(-1.0, 3.0)), _within(4.0),
)

# service -> [(key name, strategy)]: every key each service subscribes to (None: ingress's ROS 2 Odometry key)
CASES: dict[str, list[tuple[str | None, st.SearchStrategy]]] = {
    "ingress": [("odom_raw", payloads(State, valid_state()))],
    "ingress_ros2": [(None, cdr_inputs)],
    "terrain": [("state", payloads(State, valid_state(plain))), ("base_cmd", payloads(BaseCommand, base_commands))],
    "planner": [
        ("terrain_weights", payloads(TerrainWeights)),
        ("task", payloads(Task, extreme_tasks)),
        ("state", st.one_of(junk(State), plausible_states)),
    ],
    "egress": [("estop", payloads(EStop)), ("cmd", payloads(Command, commands))],
    "sim": [("base_cmd", payloads(BaseCommand, base_commands))],
}


@pytest.mark.parametrize("name", list(CASES))
def test_fuzz_service(stack: Stack, name: str) -> None:
    t = stack.targets[name]
    t_start = time.monotonic()
    for key_name, strategy in CASES[name]:
        fuzz_key(stack, name, key_name, strategy, key=ROS2_KEY if key_name is None else None)
    # the heartbeat after the last payload was taken: every payload counted, those decode refuses as rejected
    time.sleep(3.0 / HEARTBEAT_HZ)
    hb = stack.watch.hb(t.robot, t.kind)
    assert hb is not None and hb.received >= len(t.sent), hb
    assert hb.rejected >= max(1, t.must_reject), (t.must_reject, hb)
    assert_still_working(stack, name, time.monotonic())
    assert_outputs_valid(stack, t.robot)
    log = t.process.log()
    assert "Traceback" not in log and '"exc":' not in log, f"{name} logged an exception:\n{log[-3000:]}"
    assert t.process.alive()
    assert time.monotonic() - t_start < 300


def test_recorder_and_viewer_take_everything(stack: Stack) -> None:
    """Both see every key: junk of their own here, and whatever the service tests sent before."""
    fuzz_key(stack, "recorder", "state", junk(State))
    must_reject = sum(t.must_reject for t in stack.targets.values())
    viewer = stack.targets["viewer"]
    # the viewer decodes everything it sees (its channel does not drop): it refused at least what decode refuses
    assert wait_for(lambda: stack.watch.hb("f_all", "viewer").rejected >= must_reject, 30.0), (
        must_reject, stack.watch.hb("f_all", "viewer"), viewer.process.log()[-2000:]
    )
    recorder = stack.targets["recorder"]
    assert recorder.process.stop() == 0, recorder.process.log()[-2000:]
    with open(stack.record, "rb") as f:
        in_file: dict[str, set[bytes]] = {}
        for _, channel, message in make_reader(f).iter_messages():
            topic = channel.topic.removesuffix("/_rejected")  # hostile payloads may go to a side channel
            in_file.setdefault(topic, set()).add(_digest(message.data))
    for key, datas in stack.sent_by_key.items():
        if not key.startswith("gpmppi/"):
            continue  # the ROS 2 key is outside gpmppi/**
        missing = [d[:80] for d in datas if _digest(d) not in in_file.get(key, set())]
        assert not missing, f"{key}: {len(missing)} of {len(datas)} payloads not recorded, e.g. {missing[:3]}"
    for name in ("recorder", "viewer"):
        log = stack.targets[name].process.log()
        assert "Traceback" not in log and '"exc":' not in log, f"{name} logged an exception:\n{log[-3000:]}"
    assert viewer.process.alive()


def fresh(x: float) -> bytes:
    msg = State(x=x, y=0.0, theta=0.0, v=0.5, omega=0.0)
    msg.header.stamp_ns = time.time_ns()
    return encode(msg)


def fresh_command(v_ref: float, omega_ref: float) -> bytes:
    msg = Command(v_ref=v_ref, omega_ref=omega_ref)
    msg.header.stamp_ns = time.time_ns()  # egress refuses commands older than max_command_age_s
    return encode(msg)


def assert_still_working(stack: Stack, name: str, since: float) -> None:
    """The service still does its job on valid input after the fuzz: its main output appears."""
    s, t = stack.session, stack.targets[name]
    r = t.robot
    if name == "planner":
        task = Task(kind="lane", centerline=[[float(np.cos(a)) * 5, float(np.sin(a)) * 5]
                                             for a in np.linspace(0, 2 * np.pi, 40, endpoint=False)])
        s.put(key_for("task", robot=r), encode(task))
    if name == "egress":
        s.put(key_for("estop", robot=r), encode(EStop(engaged=False, reason="fuzz done")))
    time.sleep(0.2)
    nudges = {
        "ingress": lambda: s.put(key_for("odom_raw", robot=r), fresh(5.0)),
        "ingress_ros2": lambda: s.put(ROS2_KEY, ros2.odometry_cdr(np.array([5.0, 0, 0, 0.5, 0]), time.time_ns())),
        "planner": lambda: s.put(key_for("state", robot=r), fresh(5.0)),
        "terrain": lambda: s.put(key_for("state", robot=r), fresh(5.0)),
        "egress": lambda: s.put(key_for("cmd", robot=r), fresh_command(0.3, 0.1)),
        "sim": lambda: None,  # publishes odometry on its own
    }
    output = {"ingress": "state", "ingress_ros2": "state", "planner": "cmd", "terrain": "terrain_weights",
              "egress": "base_cmd", "sim": "odom_raw"}[name]

    def produced() -> bool:
        nudges[name]()
        return bool(stack.watch.on(key_for(output, robot=r), since))

    assert wait_for(produced, 30.0, 0.1), f"{name}: no {output} after the fuzz:\n{t.process.log()[-2000:]}"
    if name == "egress":
        base = [decode(BaseCommand, d) for d in stack.watch.on(key_for("base_cmd", robot=r), since)]
        assert wait_for(lambda: any(decode(BaseCommand, d).v > 0 for d in
                                    stack.watch.on(key_for("base_cmd", robot=r), since)), 5.0), base[-5:]


def assert_outputs_valid(stack: Stack, robot: str) -> None:
    """Every sample published in this robot's namespace (not one this test sent) decodes strictly: finite, in
    the schema; egress's within its limits."""
    sent = {_digest(d) for ds in stack.sent_by_key.values() for d in ds}
    with stack.watch.lock:
        samples = [(k, d) for _, k, d in stack.watch.samples if k.startswith(f"gpmppi/{robot}/")]
    checked = 0
    for key, data in samples:
        if _digest(data) in sent:
            continue
        msg: Message = decode(model_for_key(key), data)  # raises on a non-finite or malformed output
        checked += 1
        if isinstance(msg, BaseCommand):
            assert -0.5 - 1e-9 <= msg.v <= 2.0 + 1e-9 and abs(msg.omega) <= 3.1416 + 1e-9, msg
    assert checked >= 10, (robot, checked)
