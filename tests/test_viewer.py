"""The rerun view: geometry, the message -> rerun mapping through the offline converter (a real MCAP in, a real
.rrd out, read back with rerun's own reader), linear growth, bad input, and the viewer's newest-wins ring."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from schemas import BaseCommand, Heartbeat, State, TerrainWeights
from services.recording.mcap_writer import McapWriter
from services.view import geometry as geo
from services.viewer import Ring
from tools.bench_view import synthetic_log
from tools.replay_rerun import convert, main

rr = pytest.importorskip("rerun")


def read_rrd(path: Path) -> tuple[Counter[str], set[str], list[str]]:
    """(temporal rows per entity, static entities, event texts) of an .rrd, by rerun's own reader."""
    store = rr.chunk.RrdReader(path).stream().collect()
    rows: Counter[str] = Counter()
    static: set[str] = set()
    events: list[str] = []
    for chunk in store.stream():
        if chunk.is_static:
            static.add(chunk.entity_path)
            continue
        rows[chunk.entity_path] += chunk.num_rows
        if chunk.entity_path == "/events":
            batch = chunk.to_record_batch()
            col = next(n for n in batch.schema.names if n.endswith("TextLog:text"))
            events += [t for cell in batch.column(col).to_pylist() for t in (cell or [])]
    return rows, static, events


# ---- geometry -----------------------------------------------------------------------------------
def test_tightened_bounds_sit_at_the_tightened_half_width_from_the_centre() -> None:
    a = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    centre = np.stack([10 * np.cos(a), 10 * np.sin(a)], 1)
    phi = np.linspace(0.1, 0.9, 20)
    plan_xy = np.stack([10.3 * np.cos(phi), 10.3 * np.sin(phi)], 1)  # off the centre, as a plan is
    r = np.linspace(1.7, 1.2, 20)
    left, right = geo.tightened_bounds(plan_xy, r, centre, closed=True)
    # on a circle of radius 10, the left (inner, counter-clockwise lane) bound is at 10 - r, the right at 10 + r
    np.testing.assert_allclose(np.linalg.norm(left, axis=1), 10 - r, atol=2e-3)
    np.testing.assert_allclose(np.linalg.norm(right, axis=1), 10 + r, atol=2e-3)


def test_ellipses_lie_at_two_sigma() -> None:
    covs = np.array([[0.04, 0.01, 0.02], [0.09, -0.02, 0.01], [1e-4, 0.0, 1e-4]])
    centres = np.array([[1.0, 2.0], [-3.0, 0.5], [0.0, 0.0]])
    curves = geo.ellipses(centres, covs)
    for c, (sxx, sxy, syy), pts in zip(centres, covs, curves, strict=True):
        d = pts - c
        inv = np.linalg.inv(np.array([[sxx, sxy], [sxy, syy]]))
        np.testing.assert_allclose(np.einsum("ni,ij,nj->n", d, inv, d), 4.0, rtol=1e-6)
        np.testing.assert_allclose(pts[0], pts[-1], atol=1e-12)  # closed
    assert geo.pack_rgba(np.array([[1, 2, 3, 4]], dtype=np.uint8))[0] == 0x01020304


def test_cost_colours_rank_low_to_high_and_robot_points_forward() -> None:
    colors = geo.cost_colors(np.array([5.0, 1.0, 1e9, np.inf]))
    # cheapest teal-ish (green > red), the most expensive red (red > green)
    assert colors[1][1] > colors[1][0] and colors[3][0] > colors[3][1]
    assert colors.dtype == np.uint8 and colors.shape == (4, 4)
    outline = geo.robot_outline(1.0, 2.0, np.pi / 2)
    nose = outline[np.argmax(np.linalg.norm(outline - [1.0, 2.0], axis=1) * (outline[:, 1] > 2.0))]
    np.testing.assert_allclose(nose, [1.0, 2.32], atol=1e-9)  # heading +y: the nose is straight ahead


# ---- the mapping, via the converter -------------------------------------------------------------
def test_replay_to_rerun_writes_the_map_and_time_series(tmp_path: Path) -> None:
    log = tmp_path / "run.mcap"
    synthetic_log(log, 12.0)
    out = tmp_path / "out.rrd"
    result = convert(log, "save", str(out))
    assert result["messages"] > 1000 and result["skipped"] == {}
    assert 11.0 < result["log_duration_s"] < 12.5 and result["wall_s"] > 0
    rows, static, events = read_rrd(out)
    for entity in ("/map/lane/edges", "/map/lane/centre"):
        assert entity in static
    n_states = 120
    assert rows["/plots/v/state"] == n_states and rows["/plots/omega/state"] == n_states
    assert rows["/map/robot"] == n_states
    assert rows["/plots/v/cmd"] == n_states and rows["/plots/v/base"] == 240
    for entity in ("/map/plan/nominal", "/map/plan/covariance", "/map/lane/tightened", "/plots/cost/min",
                   "/plots/tightening/last", "/plots/critics/deviation", "/plots/critics/terminal",
                   "/plots/samples/effective"):  # fmt: skip
        assert rows[entity] == n_states, entity
    assert rows["/plots/terrain/asphalt"] == rows["/plots/terrain/tile"] == 84  # 7 Hz
    assert rows["/map/plan/rollouts"] == n_states // 2  # samples_every = 2
    assert rows["/plots/planner/total"] == n_states - 5  # the start-up plans are not plotted
    # the driven path: strips of 50 states, each a new entity; every state extends the current strip
    path_rows = {e: n for e, n in rows.items() if e.startswith("/map/driven_path/")}
    assert sorted(path_rows) == ["/map/driven_path/00000", "/map/driven_path/00001", "/map/driven_path/00002"]
    assert sum(path_rows.values()) == n_states - 1
    assert any("planner start-up" in e for e in events) and any("task: lane" in e for e in events)


def test_events_from_watchdog_rejections_and_restarts(tmp_path: Path) -> None:
    log = tmp_path / "events.mcap"
    t0 = 1_700_000_000_000_000_000
    with McapWriter(log) as w:
        for i, reason in enumerate(["planner", "limit", "planner", "watchdog", "watchdog", "planner", "estop"]):
            bc = BaseCommand(v=0.0, omega=0.0, reason=reason)
            bc.header.stamp_ns = t0 + i * 50_000_000
            w.write("gpmppi/r1/base/cmd", bc, log_time_ns=bc.header.stamp_ns)
        hbs = [
            Heartbeat(service="ingress", received=10, published=10),
            Heartbeat(service="ingress", received=20, rejected=3, published=20, last_error="state: stale by 2 s"),
            Heartbeat(service="ingress", received=30, rejected=3, published=30, status="degraded"),
            Heartbeat(service="ingress", received=1, published=1),  # a new process: counters from 0
        ]
        for i, hb in enumerate(hbs):
            hb.header.stamp_ns, hb.header.seq = t0 + i * 1_000_000_000, [0, 1, 2, 0][i]
            w.write("gpmppi/r1/health/ingress", hb, log_time_ns=hb.header.stamp_ns)
        # egress limiting its ramps is routine shaping: its flag and count flap every second and are no event
        for i in range(4):
            hb = Heartbeat(service="egress", received=10 * (i + 1), published=20 * (i + 1),
                           counts={"limited": 5 * i, "watchdog": int(i == 3)}, flags={"limited": i % 2 == 1})
            hb.header.stamp_ns, hb.header.seq = t0 + i * 1_000_000_000, i
            w.write("gpmppi/r1/health/egress", hb, log_time_ns=hb.header.stamp_ns)
    out = tmp_path / "events.rrd"
    convert(log, "save", str(out))
    _, _, events = read_rrd(out)
    text = "\n".join(events)
    assert "watchdog override" in text and "estop override" in text and "override ended" in text
    assert "limit" not in text  # a limited planner command is not an event, nor egress's limiting count or flag
    assert "egress: watchdog +1 (now 1)" in text
    assert "ingress: rejected 3 input(s) (total 3): state: stale by 2 s" in text
    assert "ingress: status ok -> degraded" in text and "ingress: restarted" in text


def test_unknown_ground_is_plotted_with_the_weights_and_its_decision_changes_are_events(tmp_path: Path) -> None:
    log = tmp_path / "unknown.mcap"
    t0 = 1_700_000_000_000_000_000
    # P(unknown) crosses 0.5 back and forth; only the service's hysteretic decision makes events (on, then off)
    probs = [0.0, 0.2, 0.7, 0.4, 0.9, 0.3, 0.1, 0.05]
    active = [False, False, True, True, True, True, False, False]
    with McapWriter(log) as w:
        for i, (p, a) in enumerate(zip(probs, active, strict=True)):
            msg = TerrainWeights(names=["asphalt", "grass"], weights=[0.1, 0.9], unknown=p, unknown_active=a,
                                 unknown_channel="free-run" if i else "")
            msg.header.stamp_ns = t0 + i * 100_000_000
            w.write("gpmppi/r1/terrain/weights", msg, log_time_ns=msg.header.stamp_ns)
        # the terrain service's heartbeat carries the probability and the decision: no events of their own
        for i in range(3):
            hb = Heartbeat(service="terrain", counts={"unknown_permille": 300 * i, "unknown_entered": i},
                           flags={"unknown_ground": i == 1, "unknown_free_run": i == 1})
            hb.header.stamp_ns, hb.header.seq = t0 + i * 1_000_000_000, i
            w.write("gpmppi/r1/health/terrain", hb, log_time_ns=hb.header.stamp_ns)
    out = tmp_path / "unknown.rrd"
    convert(log, "save", str(out))
    rows, _, events = read_rrd(out)
    assert rows["/plots/terrain/unknown"] == len(probs) and rows["/plots/terrain/grass"] == len(probs)
    unknown = [e for e in events if "ground" in e]
    assert len(unknown) == 2, events
    assert "ground unknown" in unknown[0] and "P(unknown) 0.70" in unknown[0] and "nearest grass" in unknown[0]
    assert "free-run channel" in unknown[0] and "slides" in unknown[0]  # the channel that flagged it, from the message
    assert "ground known again" in unknown[1]
    assert not any(name in e for e in events for name in ("unknown_permille", "unknown_entered", "unknown_ground",
                                                          "unknown_free_run"))


def test_keys_exclude_and_time_window(tmp_path: Path) -> None:
    log = tmp_path / "run.mcap"
    synthetic_log(log, 10.0)
    out = tmp_path / "w.rrd"
    r = convert(log, "save", str(out), start_s=2.0, end_s=6.0, keys=r"/(state|plan)$", exclude="plan")
    rows, _, _ = read_rrd(out)
    assert set(rows) <= {"/plots/v/state", "/plots/omega/state", "/map/robot"} | {
        e for e in rows if e.startswith("/map/driven_path/")
    }
    assert 39 <= rows["/plots/v/state"] <= 41 and r["messages"] == rows["/plots/v/state"]
    assert 3.8 <= r["log_duration_s"] <= 4.0


@pytest.mark.slow(seconds=5)  # a stack-sized stream drawn for seconds
def test_recording_grows_linearly(tmp_path: Path) -> None:
    sizes = {}
    for seconds in (10, 20, 40):  # measured ratio 1.996 (20-40-80 s: 2.000)
        log = tmp_path / f"{seconds}.mcap"
        synthetic_log(log, float(seconds))
        convert(log, "save", str(tmp_path / f"{seconds}.rrd"))
        sizes[seconds] = (tmp_path / f"{seconds}.rrd").stat().st_size
    # doubling the run adds twice the bytes of the previous doubling (quadratic growth would add four times)
    ratio = (sizes[40] - sizes[20]) / (sizes[20] - sizes[10])
    assert 1.7 < ratio < 2.3, sizes


# ---- bad input ----------------------------------------------------------------------------------
def test_bad_files_give_clear_errors_and_leave_no_output(tmp_path: Path) -> None:
    out = tmp_path / "o.rrd"
    with pytest.raises(FileNotFoundError, match="no MCAP log at"):
        convert(tmp_path / "missing.mcap", "save", str(out))
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(ValueError, match="is empty"):
        convert(tmp_path / "empty.mcap", "save", str(out))
    (tmp_path / "text.mcap").write_text("hello, not a log\n")
    with pytest.raises(ValueError, match="not an MCAP file"):
        convert(tmp_path / "text.mcap", "save", str(out))
    with pytest.raises(ValueError, match="not one of"):
        convert(tmp_path / "text.mcap", "play", None)
    with pytest.raises(ValueError, match="optional gRPC port"):
        convert(tmp_path / "text.mcap", "serve", "not-a-port")
    with pytest.raises(ValueError, match="bad topic regex"):
        convert(tmp_path / "text.mcap", "save", str(out), keys="(")
    assert not out.exists() and not list(tmp_path.glob("*.part"))
    assert main([str(tmp_path / "text.mcap"), str(out)]) == 2


def test_unknown_schemas_and_non_json_channels_are_named_and_skipped(tmp_path: Path) -> None:
    log = tmp_path / "mixed.mcap"
    st = State(x=1.0, y=2.0, theta=0.0, v=0.5, omega=0.0)
    st.header.stamp_ns = 1_700_000_000_000_000_000
    with open(log, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="test")
        good = w.register_channel(topic="gpmppi/r1/state", message_encoding="json", schema_id=0)
        cdr_schema = w.register_schema(name="geometry_msgs/msg/Twist", encoding="ros2msg", data=b"float64 x")
        cdr = w.register_channel(topic="gpmppi/r1/cmd", message_encoding="cdr", schema_id=cdr_schema)
        unknown = w.register_channel(topic="other/thing", message_encoding="json", schema_id=0)
        for i in range(5):
            t = st.header.stamp_ns + i * 100_000_000
            w.add_message(good, log_time=t, publish_time=t, data=st.model_dump_json().encode())
            w.add_message(cdr, log_time=t, publish_time=t, data=b"\x00\x01\x00\x00binary")
            w.add_message(unknown, log_time=t, publish_time=t, data=b'{"a": 1}')
        w.finish()
    out = tmp_path / "mixed.rrd"
    r = convert(log, "save", str(out))
    assert r["messages"] == 5
    assert r["skipped"] == {"gpmppi/r1/cmd": 5, "other/thing": 5}
    assert "other/thing" in r["skipped_reasons"] and r["skipped_reasons"]["gpmppi/r1/cmd"]
    rows, _, _ = read_rrd(out)
    assert rows["/plots/v/state"] == 5


def test_truncated_log_converts_what_is_there(tmp_path: Path) -> None:
    log = tmp_path / "full.mcap"
    synthetic_log(log, 6.0)
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    r = convert(cut, "save", str(tmp_path / "cut.rrd"))
    assert 0 < r["messages"] < 600 and any("linear scan" in n or "incomplete" in n for n in r.get("notes", []))
    assert (tmp_path / "cut.rrd").stat().st_size > 0


def test_cli_entry_prints_the_result(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "run.mcap"
    synthetic_log(log, 3.0)
    assert main([str(log), str(tmp_path / "o.rrd")]) == 0
    assert json.loads(capsys.readouterr().out)["messages"] > 100


# ---- newest-wins ring ---------------------------------------------------------------------------
def test_ring_never_blocks_and_drops_the_oldest() -> None:
    ring = Ring(3)
    for i in range(5):
        ring.push(i)  # type: ignore[arg-type]
    assert ring.dropped == 2
    assert [ring.pop(), ring.pop(), ring.pop(), ring.pop()] == [2, 3, 4, None]


def test_goal_task_shows_obstacles_inflation_and_goal(tmp_path: Path) -> None:
    from schemas import Circle, Command, Plan, Task

    log = tmp_path / "goal.mcap"
    t0 = 1_700_000_000_000_000_000
    task = Task(kind="goal", goal=[8.0, 0.0], obstacles=[Circle(x=4.0, y=0.2, r=0.5), Circle(x=6.0, y=-1.0, r=0.7)])
    task.header.stamp_ns = t0
    with McapWriter(log) as w:
        w.write("gpmppi/r1/task", task, log_time_ns=t0)
        for i in range(10):
            t = t0 + (i + 1) * 100_000_000
            plan = Plan(
                command=Command(v_ref=1.0, omega_ref=0.0), controls=[[1.0, 0.0]] * 10,
                states=[[0.1 * k, 0.0, 0.0, 1.0, 0.0] for k in range(11)], cov_xy=[[1e-3, 0.0, 1e-3]] * 11,
                tightened=[0.05 * k for k in range(11)],
                samples=[[[0.1 * k, 0.01 * j] for k in range(11)] for j in range(4)],
                sample_costs=[1.0, 2.0, 3.0, 4.0],
            )  # fmt: skip
            plan.header.stamp_ns, plan.header.seq = t, i
            w.write("gpmppi/r1/plan", plan, log_time_ns=t)
    out = tmp_path / "goal.rrd"
    convert(log, "save", str(out))
    rows, static, events = read_rrd(out)
    assert {"/map/obstacles", "/map/goal"} <= static
    assert rows["/map/obstacles_inflated"] == 10 and rows["/plots/tightening/last"] == 10
    assert "/map/lane/tightened" not in rows and any("task: goal" in e for e in events)


def test_a_costmap_is_drawn_once_per_grid_at_its_lethal_cells(tmp_path: Path) -> None:
    from schemas import Header, OccupancyGrid

    values = np.zeros((4, 5), dtype=int)
    values[1, 3] = 100
    values[2, 0] = 60
    grid = OccupancyGrid(header=Header(frame_id="odom"), resolution=0.5, width=5, height=4, origin_x=1.0, origin_y=2.0,
                         origin_yaw=np.pi / 2, data=values.reshape(-1).tolist())
    centres, radius = geo.lethal_cells(grid)
    # cell (row 1, column 3): (1.75, 0.75) m along the grid's axes, the grid's x along the world's y
    assert centres == pytest.approx(np.array([[1.0 - 0.75, 2.0 + 1.75]])) and radius == 0.25
    log = tmp_path / "grid.mcap"
    t0 = 1_700_000_000_000_000_000
    with McapWriter(log) as w:
        for i in range(3):  # re-published with new stamps: drawn once
            grid.header.stamp_ns = t0 + i * 100_000_000
            w.write("gpmppi/r1/costmap", grid, log_time_ns=grid.header.stamp_ns)
    out = tmp_path / "grid.rrd"
    convert(log, "save", str(out))
    _rows, static, events = read_rrd(out)
    assert "/map/costmap" in static
    assert [e for e in events if "costmap" in e] == ["costmap: 5 x 4 cells of 0.5 m, 1 lethal"]


def test_the_foxglove_scene_draws_a_costmaps_lethal_cells() -> None:
    pytest.importorskip("foxglove")
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    from schemas import Header, OccupancyGrid
    from services.view.foxglove_scene import FoxgloveSceneMapper, schema_of

    values = np.zeros((4, 5), dtype=int)
    values[1, 3] = values[2, 4] = 100
    grid = OccupancyGrid(header=Header(stamp_ns=5, frame_id="odom"), resolution=0.5, width=5, height=4,
                         data=values.reshape(-1).tolist())
    (out,) = FoxgloveSceneMapper().map("gpmppi/r1/costmap", grid, 1)
    assert out.topic == "scene/r1/task"
    schema = schema_of(out.topic)  # Foxglove's protobuf schema: decode what it would
    pool = descriptor_pool.DescriptorPool()
    for f in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
        pool.Add(f)
    update = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name)).FromString(out.data)
    (entity,) = update.entities
    assert entity.id == "costmap" and len(entity.cubes) == 2
    assert (entity.cubes[0].pose.position.x, entity.cubes[0].pose.position.y) == (1.75, 0.75)
