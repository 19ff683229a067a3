"""The Foxglove view: the live server speaks Foxglove's WebSocket protocol (a real client, a real router), the
recorder's scene channels and `gpmppi replay --foxglove-scene` write Foxglove's schemas into the MCAP, and the
shipped layout names only topics that are served."""

from __future__ import annotations

import base64
import json
import struct
import time
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

from schemas import Command, EStop, Heartbeat, Plan, State, Task, encode
from services.view.foxglove_scene import SCENE_SCHEMAS, scene_topics
from tests.zenoh_helpers import Collector, ServiceProcess, client, free_port, heartbeats, router, settings, wait_for
from tools.bench_foxglove import layout_topics

pytest.importorskip("foxglove")
websockets_sync = pytest.importorskip("websockets.sync.client")

REPO = Path(__file__).resolve().parents[1]
# Foxglove's WebSocket protocol: foxglove-sdk 0.30's server names it `foxglove.sdk.v1` (the same protocol as
# `foxglove.websocket.v1`, renamed; it refuses the old name); a client offers both, as Foxglove does
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
LAYOUT = REPO / "deploy" / "foxglove" / "gpmppi-layout.json"


def protobuf_class(schema_name: str, descriptor_set: bytes) -> Any:
    """The message class of `schema_name` from a serialized FileDescriptorSet (Foxglove's protobuf schemas)."""
    files = descriptor_pb2.FileDescriptorSet.FromString(descriptor_set)
    pool = descriptor_pool.DescriptorPool()
    for f in files.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def _stack_messages(robot: str, i: int) -> list[tuple[str, bytes]]:
    """One cycle of what the stack publishes: a state, a command, a plan with rollouts, a heartbeat."""
    t = time.time_ns()
    st = State(x=0.1 * i, y=0.2, theta=0.3, v=1.0, omega=0.1)
    st.header.stamp_ns, st.header.seq = t, i
    cmd = Command(v_ref=1.0, omega_ref=0.1)
    cmd.header.stamp_ns, cmd.header.seq = t, i
    rng = np.random.default_rng(i)
    plan = Plan(
        command=cmd, controls=[[1.0, 0.0]] * 10, states=[[0.1 * k, 0.01 * k, 0.0, 1.0, 0.0] for k in range(11)],
        cov_xy=[[1e-3 * k, 0.0, 2e-3 * k] for k in range(11)], tightened=[1.5 - 0.01 * k for k in range(11)],
        samples=rng.normal(size=(6, 11, 2)).round(3).tolist(), sample_costs=rng.gamma(2.0, 1.0, 6).tolist(),
        timings_ms={"total": 5.0},
    )  # fmt: skip
    plan.header.stamp_ns, plan.header.seq = t, i
    hb = Heartbeat(service="planner", rate_hz=10.0)
    hb.header.stamp_ns, hb.header.seq = t, i
    return [
        (f"gpmppi/{robot}/state", encode(st)),
        (f"gpmppi/{robot}/cmd", encode(cmd)),
        (f"gpmppi/{robot}/plan", encode(plan)),
        (f"gpmppi/{robot}/health/planner", encode(hb)),
        (f"gpmppi/{robot}/estop", encode(EStop(engaged=i % 20 == 10))),
    ]


def lane_task() -> Task:
    a = np.linspace(0.0, 2 * np.pi, 60, endpoint=False)
    return Task(kind="lane", centerline=np.stack([5 * np.cos(a), 5 * np.sin(a)], 1).tolist(), closed=True)


def test_live_server_speaks_the_foxglove_websocket_protocol(tmp_path: Path) -> None:
    """A WebSocket client (subprotocol foxglove.websocket.v1) gets every channel advertised with its schema,
    subscribes, and receives messages that validate against the advertised JSON Schemas (our keys) or decode with
    Foxglove's protobuf schemas (the scene); the shipped layout's topics are all among those advertised."""
    port, ws_port = free_port(), free_port()
    robot = "jackal"  # the layout's robot
    with router(port):
        observer = client(port)
        col = Collector(observer, f"gpmppi/{robot}/health/foxglove")
        service = ServiceProcess("foxglove", {**settings("foxglove", port, robot), "port": ws_port}, tmp_path)
        try:
            assert wait_for(lambda: len(heartbeats(col, robot, "foxglove")) >= 1, 60.0), service.log()
            # no client: nothing is decoded, so a malformed payload on a served key is not even looked at
            seen = len(heartbeats(col, robot, "foxglove"))
            observer.put(f"gpmppi/{robot}/state", b"{not json")
            for key, payload in _stack_messages(robot, 0)[1:]:  # all but the state, so the malformed one is taken
                observer.put(key, payload)
            assert wait_for(lambda: len(heartbeats(col, robot, "foxglove")) >= seen + 2, 15.0)  # a loop cycle or more
            assert heartbeats(col, robot, "foxglove")[-1].counts.get("unread", 0) >= 5
            assert heartbeats(col, robot, "foxglove")[-1].rejected == 0
            with websockets_sync.connect(f"ws://127.0.0.1:{ws_port}", subprotocols=SUBPROTOCOLS, open_timeout=10) as ws:
                assert ws.subprotocol in SUBPROTOCOLS
                channels: dict[int, dict] = {}
                server_info = None
                deadline = time.monotonic() + 10
                wanted = {*scene_topics(robot), f"gpmppi/{robot}/state", f"gpmppi/{robot}/plan", f"gpmppi/{robot}/task"}
                while not wanted <= {c["topic"] for c in channels.values()} and time.monotonic() < deadline:
                    frame = json.loads(ws.recv(timeout=5))
                    if frame["op"] == "serverInfo":
                        server_info = frame
                    elif frame["op"] == "advertise":
                        channels.update({c["id"]: c for c in frame["channels"]})
                assert server_info is not None
                assert wanted <= {c["topic"] for c in channels.values()}
                for c in channels.values():  # every channel comes with its schema
                    assert c["schemaName"] and c["schema"], c
                    if c["topic"].startswith("gpmppi/"):
                        assert (c["encoding"], c["schemaEncoding"]) == ("json", "jsonschema")
                        jsonschema.Draft202012Validator.check_schema(json.loads(c["schema"]))
                    else:
                        assert (c["encoding"], c["schemaEncoding"]) == ("protobuf", "protobuf")
                        assert c["schemaName"] == "foxglove." + SCENE_SCHEMAS[c["topic"].rsplit("/", 1)[-1]]
                ws.send(json.dumps({
                    "op": "subscribe", "subscriptions": [{"id": cid, "channelId": cid} for cid in channels],
                }))  # fmt: skip
                observer.put(f"gpmppi/{robot}/task", encode(lane_task()))
                received: dict[str, list[bytes]] = {}
                deadline = time.monotonic() + 30
                i = 0
                needed = {*scene_topics(robot), f"gpmppi/{robot}/state", f"gpmppi/{robot}/plan", f"gpmppi/{robot}/cmd"}
                while not needed <= set(received) and time.monotonic() < deadline:
                    for key, payload in _stack_messages(robot, i):
                        observer.put(key, payload)
                    if i % 10 == 0:
                        observer.put(f"gpmppi/{robot}/task", encode(lane_task()))
                    i += 1
                    try:
                        while True:
                            frame = ws.recv(timeout=0.05)
                            if isinstance(frame, bytes):
                                assert frame[0] == 0x01  # message data
                                sub_id, _log_time = struct.unpack_from("<IQ", frame, 1)
                                channel = channels.get(sub_id)
                                if channel is not None:
                                    received.setdefault(channel["topic"], []).append(frame[13:])
                            elif json.loads(frame)["op"] == "advertise":
                                for c in json.loads(frame)["channels"]:
                                    channels[c["id"]] = c
                    except TimeoutError:
                        pass
                assert needed <= set(received), (sorted(received), service.log()[-3000:])
                # read now: the same malformed payload is decoded, and refused
                observer.put(f"gpmppi/{robot}/state", b"{not json")
                assert wait_for(lambda: heartbeats(col, robot, "foxglove")[-1].rejected >= 1, 15.0), service.log()
        finally:
            code = service.stop(20.0)
            observer.close()
    assert code == 0, service.log()
    by_topic = {c["topic"]: c for c in channels.values()}
    for topic, payloads in received.items():
        c = by_topic[topic]
        if c["encoding"] == "json":
            validator = jsonschema.Draft202012Validator(json.loads(c["schema"]))
            for p in payloads:
                validator.validate(json.loads(p))
        else:
            cls = protobuf_class(c["schemaName"], base64.b64decode(c["schema"]))
            for p in payloads:
                cls.FromString(p)
    named = layout_topics(json.loads(LAYOUT.read_text()))
    assert named and named <= set(by_topic), sorted(named - set(by_topic))
    # the scene says what we sent
    tf_cls = protobuf_class("foxglove.FrameTransforms", base64.b64decode(by_topic[f"scene/{robot}/tf"]["schema"]))
    tf = tf_cls.FromString(received[f"scene/{robot}/tf"][-1]).transforms[0]
    assert (tf.parent_frame_id, tf.child_frame_id) == ("map", "base_link") and tf.translation.y == pytest.approx(0.2)
    scene_cls = protobuf_class("foxglove.SceneUpdate", base64.b64decode(by_topic[f"scene/{robot}/plan"]["schema"]))
    ids = {e.id for p in received[f"scene/{robot}/plan"] for e in scene_cls.FromString(p).entities}
    assert {"plan/nominal", "plan/covariance", "plan/rollouts"} <= ids
    ids = {e.id for p in received[f"scene/{robot}/task"] for e in scene_cls.FromString(p).entities}
    assert {"lane/edges", "lane/centre"} <= ids


def _check_scene_mcap(path: Path, robot: str) -> dict[str, int]:
    """Every scene channel of the MCAP at `path` has Foxglove's schema and every message decodes with it;
    returns the messages per scene topic."""
    counts: dict[str, int] = {}
    classes: dict[int, Any] = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages():
            if not channel.topic.startswith("scene/"):
                continue
            assert schema is not None and schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
            assert schema.name == "foxglove." + SCENE_SCHEMAS[channel.topic.rsplit("/", 1)[-1]]
            if schema.id not in classes:
                classes[schema.id] = protobuf_class(schema.name, schema.data)
            classes[schema.id].FromString(message.data)
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    assert set(scene_topics(robot)) - {f"scene/{robot}/events"} <= set(counts), counts
    return counts


def test_recorder_writes_the_scene_channels(tmp_path: Path) -> None:
    """With `foxglove_scene: true` the recorder writes the scene beside the messages: Foxglove's schemas, every
    message decodes, and the gpmppi channels read back as before."""
    from services.recording.mcap_io import read_messages

    port = free_port()
    robot = "r1"
    out = tmp_path / "rec.mcap"
    with router(port):
        observer = client(port)
        col = Collector(observer, f"gpmppi/{robot}/health/recorder")
        rec = ServiceProcess(
            "recorder", settings("recorder", port, robot, path=str(out), foxglove_scene=True), tmp_path
        )
        try:
            assert wait_for(lambda: len(heartbeats(col, robot, "recorder")) >= 1, 60.0), rec.log()
            observer.put(f"gpmppi/{robot}/task", encode(lane_task()))
            for i in range(20):
                for key, payload in _stack_messages(robot, i):
                    observer.put(key, payload)
                time.sleep(0.01)
            assert wait_for(lambda: heartbeats(col, robot, "recorder")[-1].received >= 101, 15.0), rec.log()
        finally:
            code = rec.stop(20.0)
            observer.close()
    assert code == 0, rec.log()
    counts = _check_scene_mcap(out, robot)
    assert counts[f"scene/{robot}/tf"] == 20
    keys = {k for k, _, _ in read_messages(out)}  # the scene is not a gpmppi message: left out, no warning
    assert f"gpmppi/{robot}/state" in keys and not any(k.startswith("scene/") for k in keys)


def test_replay_adds_the_scene_offline_and_it_grows_linearly(tmp_path: Path) -> None:
    """`gpmppi replay LOG --foxglove-scene OUT.mcap`: the recording with its scene added; a run twice as long gives
    about twice the bytes (linear growth)."""
    from typer.testing import CliRunner

    from tools.bench_view import synthetic_log
    from tools.cli import app

    sizes = {}
    for seconds in (15.0, 30.0):
        log = tmp_path / f"log{seconds:g}.mcap"
        synthetic_log(log, seconds, robot="r1")
        out = tmp_path / f"scene{seconds:g}.mcap"
        result = CliRunner().invoke(app, ["replay", str(log), "--foxglove-scene", str(out), "--json"])
        assert result.exit_code == 0, result.output
        counts = _check_scene_mcap(out, "r1")
        assert counts["scene/r1/tf"] == int(seconds * 10)
        sizes[seconds] = (out.stat().st_size, log.stat().st_size)
    added = {s: out_b - log_b for s, (out_b, log_b) in sizes.items()}
    assert 1.6 < added[30.0] / added[15.0] < 2.4, sizes


def test_layout_names_only_served_topics() -> None:
    """Every topic the shipped layout names is a channel the server serves for the default robot (its fixed keys
    and its scene; the live test checks the same against a running server's advertisements)."""
    from schemas import KEYS

    layout = json.loads(LAYOUT.read_text())
    served = {t.format(robot="jackal") for t, _ in (v for v in KEYS.values()) if "{service}" not in t}
    served |= set(scene_topics("jackal"))
    named = layout_topics(layout)
    assert named, "the layout names no topics"
    assert named <= served, sorted(named - served)
    assert {"scene/jackal/plan", "gpmppi/jackal/state", "gpmppi/jackal/plan"} <= named


def _plan_at(stamp_ns: int, seq: int) -> Plan:
    plan = Plan(
        command=Command(v_ref=1.0, omega_ref=0.0), controls=[[1.0, 0.0]] * 10,
        states=[[0.1 * k, 0.0, 0.0, 1.0, 0.0] for k in range(11)],
        cov_xy=[[1e-3 * k, 0.0, 1e-3 * k] for k in range(11)],
        samples=[[[0.1 * k, 0.01 * j] for k in range(11)] for j in range(4)], sample_costs=[1.0, 2.0, 3.0, 4.0],
    )  # fmt: skip
    plan.header.stamp_ns, plan.header.seq = stamp_ns, seq
    return plan


def test_the_mapper_makes_only_the_topics_asked_for() -> None:
    """`map(..., wanted)` makes only the scene topics named, and a topic left out keeps no state: the driven path
    starts when "robot" is first asked for. `scene_feeds` names what each key feeds (the task feeds the plan)."""
    from services.view.foxglove_scene import FoxgloveSceneMapper, scene_feeds

    mapper = FoxgloveSceneMapper()
    t = 1_000_000_000
    state = State(x=1.0, y=2.0, theta=0.0, v=0.5, omega=0.0)
    state.header.stamp_ns = t
    assert [m.topic for m in mapper.map("gpmppi/r1/state", state, t, {"tf"})] == ["scene/r1/tf"]
    assert mapper.map("gpmppi/r1/state", state, t, set()) == []
    assert mapper.map("gpmppi/r1/estop", EStop(engaged=True), t, {"tf", "plan"}) == []
    assert {m.topic for m in mapper.map("gpmppi/r1/state", state, t)} == {
        f"scene/r1/{n}" for n in ("tf", "pose", "robot")
    }
    assert "robot" not in mapper.map.__self__._paths or mapper._paths["r1"].points == [[1.0, 2.0]]
    # a task not asked for is still kept: the plan's tightened bounds are drawn from it
    assert mapper.map("gpmppi/r1/task", lane_task(), t, {"plan"}) == [] and "r1" in mapper.task
    assert scene_feeds("gpmppi/r1/state") == {"tf", "pose", "robot"} and scene_feeds("gpmppi/r1/odom/raw") == set()
    assert scene_feeds("gpmppi/r1/task") == {"task", "plan", "events"} and scene_feeds("gpmppi/r1/cmd") == set()
    assert scene_feeds("gpmppi/r1/health/planner") == {"events"} and scene_feeds("elsewhere/x") == set()


def test_the_plan_scene_rate_limit_holds() -> None:
    """Plans at 10 Hz with jitter (seeded) for 20 s: the plan's scene at plan_hz (5 Hz), evenly (no gap over two
    periods), never more than T * hz + 2 over any span; plan_hz 0 draws every plan; a stamp going back (a new run)
    restarts the schedule."""
    from services.view.foxglove_scene import FoxgloveSceneMapper, RateLimit, SceneOptions

    rng = np.random.default_rng(46)
    stamps = (np.arange(200) * 100_000_000 + rng.uniform(-20e6, 20e6, 200)).astype(np.int64) + 10**12
    mapper = FoxgloveSceneMapper(SceneOptions(plan_hz=5.0))
    drawn = [int(s) for i, s in enumerate(stamps) if mapper.map("gpmppi/r1/plan", _plan_at(int(s), i), 0)]
    assert 95 <= len(drawn) <= 20 * 5 + 2, len(drawn)
    gaps = np.diff(drawn) / 1e9
    assert gaps.max() < 0.4, gaps.max()
    for span in (1.0, 3.0):  # any window of `span` seconds
        starts = np.asarray(drawn)
        counts = [np.sum((starts >= a) & (starts < a + span * 1e9)) for a in starts]
        assert max(counts) <= span * 5 + 2, (span, max(counts))
    every = FoxgloveSceneMapper(SceneOptions(plan_hz=0.0))
    assert all(every.map("gpmppi/r1/plan", _plan_at(int(s), i), 0) for i, s in enumerate(stamps[:20]))
    limit = RateLimit(5.0)
    assert limit(10**12) and not limit(10**12 + 50_000_000) and limit(10**9)  # back in time: a new schedule
    # the plan's entities: nominal, ellipses, rollouts in every drawn plan (samples_every 1 by default)
    fresh = FoxgloveSceneMapper()
    ids = {e.id for e in _scene_update(fresh.map("gpmppi/r1/plan", _plan_at(10**12, 0), 0)[0].data).entities}
    assert {"plan/nominal", "plan/covariance", "plan/rollouts"} <= ids


def _scene_update(data: bytes) -> Any:
    from foxglove import messages

    return protobuf_class("foxglove.SceneUpdate", messages.SceneUpdate.get_schema().data).FromString(data)


def test_routes_follow_what_a_client_subscribes() -> None:
    """A real server and a real client: a key's route reports readers only for the channels the client subscribed
    to (its own, or a scene topic it feeds), and none again once the client unsubscribes."""
    import foxglove

    from services.foxglove import Channels

    context = foxglove.Context()
    channels = Channels(context)
    for key in ("gpmppi/jackal/state", "gpmppi/jackal/task", "gpmppi/jackal/cmd"):
        channels.route(key)
    server = foxglove.start_server(host="127.0.0.1", port=0, context=context)
    try:
        with websockets_sync.connect(f"ws://127.0.0.1:{server.port}", subprotocols=SUBPROTOCOLS) as ws:
            ids: dict[str, int] = {}
            while not {"scene/jackal/plan", "gpmppi/jackal/cmd"} <= set(ids):
                frame = json.loads(ws.recv(timeout=5))
                if frame["op"] == "advertise":
                    ids.update({c["topic"]: c["id"] for c in frame["channels"]})
            assert all(
                channels.route(k).readers() == (False, []) for k in ("gpmppi/jackal/state", "gpmppi/jackal/task")
            )
            subs = [{"id": 1, "channelId": ids["scene/jackal/plan"]}, {"id": 2, "channelId": ids["gpmppi/jackal/cmd"]}]
            ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            assert wait_for(lambda: channels.route("gpmppi/jackal/cmd").readers() == (True, []), 5.0)
            assert channels.route("gpmppi/jackal/task").readers() == (False, ["plan"])
            assert channels.route("gpmppi/jackal/state").readers() == (False, [])
            ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": [1, 2]}))
            assert wait_for(lambda: channels.route("gpmppi/jackal/task").readers() == (False, []), 5.0)
    finally:
        server.stop()


def test_bench_summary_reads_the_spread_from_one_run() -> None:
    """`gpmppi bench foxglove`'s summary: each mode's p99 per round, the off rounds' range and spread, and how many
    rounds of the other modes stay at or under the off rounds' largest p99."""
    from tools.bench_foxglove import summarize

    def row(off: float, conn: float, stopped: float) -> dict:
        q = lambda p99: {"state_to_cmd_received": {"n": 100, "p50_ms": 8.0, "p99_ms": p99}}  # noqa: E731
        return {"off": q(off), "connected": {**q(conn), "service_cpu_s_per_s": 0.02},
                "client_stopped": {**q(stopped), "service_cpu_s_per_s": 0.01}}  # fmt: skip

    s = summarize([row(15.0, 15.5, 14.0), row(16.0, 17.0, 15.9), row(15.5, 15.2, 16.1)])
    assert s["off_p99_range_ms"] == [15.0, 16.0] and s["off_p99_spread_ms"] == 1.0
    assert s["connected_rounds_within_off_range"] == "2/3" and s["client_stopped_rounds_within_off_range"] == "2/3"
    assert s["received_p99_ms_per_round"]["connected"] == [15.5, 17.0, 15.2] and s["connected_p99_median_ms"] == 15.5
    assert s["connected_service_cpu_s_per_s"] == 0.02


def test_bench_refuses_an_unknown_subscription_in_one_line() -> None:
    """`gpmppi bench foxglove --subscribe x`: one line naming the choices, exit 2, before any process starts."""
    from typer.testing import CliRunner

    from tools.cli import app

    result = CliRunner().invoke(app, ["bench", "foxglove", "--subscribe", "everything"])
    assert result.exit_code == 2, result.output
    assert "--subscribe everything" in result.output and "layout or all" in result.output
    assert "Traceback" not in result.output
