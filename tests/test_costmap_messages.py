"""Occupancy grids at the edges: nav_msgs/OccupancyGrid CDR (rosbags) into our message and the core's grid, malformed
ones refused with their reason; the planner cycle keeps its warm start over a new grid; and a planner service over
loopback Zenoh plans among a grid it is sent, refuses one in another frame than its states' or of the wrong size
(counted in its heartbeat's rejects), and publishes the grid it plans among (so it is recorded)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from zenoh_helpers import Collector, ServiceProcess, client, free_port, heartbeats, matched_publisher, router, settings
from zenoh_helpers import wait_for as wait

from gpmppi.costmap import Costmap
from schemas import DecodeError, Header, OccupancyGrid, Plan, State, decode, encode
from services.codec.convert import costmap_from_message, costmap_to_message
from services.codec.ros2 import occupancy_grid_cdr, occupancy_grid_from_cdr

STAMP = 1_700_000_000_123_456_789


def _values() -> np.ndarray:
    v = np.zeros((30, 40), dtype=np.int8)
    v[10:20, 25:28] = 100
    v[0, :] = -1
    v[5, 5] = 60
    return v


def test_a_ros_occupancy_grid_decodes_to_ours_and_to_the_cores_grid() -> None:
    raw = occupancy_grid_cdr(_values(), 0.05, (1.0, -2.0, 0.4), STAMP, frame_id="odom")
    msg = occupancy_grid_from_cdr(raw)
    again = decode(OccupancyGrid, encode(msg))  # valid as our schema says, and through the JSON codec
    assert again == OccupancyGrid.model_validate(msg.model_dump())
    assert (msg.width, msg.height, msg.header.frame_id, msg.header.stamp_ns) == (40, 30, "odom", STAMP)
    assert msg.origin_yaw == pytest.approx(0.4) and msg.resolution == pytest.approx(0.05)
    grid = costmap_from_message(again)
    assert np.array_equal(grid.values, _values()) and grid.origin == pytest.approx((1.0, -2.0, 0.4))
    assert grid.lethal_cells.sum() == 30 and np.array_equal(costmap_from_message(costmap_to_message(
        grid, "odom")).values, grid.values)


def test_malformed_grids_are_refused_with_their_reason() -> None:
    raw = occupancy_grid_cdr(_values(), 0.05, (0.0, 0.0, 0.0), STAMP, width=41)
    with pytest.raises(ValueError, match=r"width 41 x height 30 carries 1200 values; the grid's size must match"):
        occupancy_grid_from_cdr(raw)
    with pytest.raises(ValueError, match="not a nav_msgs/msg/OccupancyGrid CDR payload"):
        occupancy_grid_from_cdr(raw[:40])
    bad = json.loads(encode(costmap_to_message(Costmap(_values(), 0.05), "odom")))
    bad["width"] = 41
    with pytest.raises(DecodeError, match=r"data has 1200 values for a grid of width 41 x height 30 = 1230"):
        decode(OccupancyGrid, json.dumps(bad).encode())


def _wall_grid(frame: str, stamp_ns: int) -> OccupancyGrid:
    """A wall across the paper scene's way, 3 m to 4 m from the start, in `frame`; the cells about it cost 30 %."""
    values = np.full((120, 120), 30, dtype=np.int16)
    values[40:80, 60:64] = 100
    return costmap_to_message(Costmap(values, 0.05, (0.0, 0.0, 0.0)), frame, stamp_ns)


@pytest.mark.slow(seconds=15)
def test_the_planner_service_plans_among_a_grid_and_refuses_bad_ones(tmp_path: Path) -> None:
    port = free_port()
    cfg = settings("planner", port, scenario="paper_obstacles", heartbeat_hz=10.0, planner={"samples": 128},
                   task_period_s=0.3)
    with router(port):
        observer = client(port)
        col = Collector(observer)
        planner = ServiceProcess("planner", cfg, tmp_path)
        try:
            hb = lambda: heartbeats(col, "r1", "planner")  # noqa: E731
            assert wait(lambda: bool(hb()), 120.0), planner.log()
            state_pub = matched_publisher(observer, "gpmppi/r1/state")
            grid_pub = matched_publisher(observer, "gpmppi/r1/costmap")

            def drive(seconds: float) -> None:
                end = time.monotonic() + seconds
                while time.monotonic() < end:
                    state_pub.put(encode(State(x=0.0, y=0.0, theta=0.7854, v=0.0, omega=0.0,
                                               header=Header(stamp_ns=time.time_ns(), frame_id="odom"))))
                    time.sleep(0.1)

            def plans() -> list[tuple[float, Plan]]:
                return [(t, decode(Plan, p)) for t, p, _ in col.on("gpmppi/r1/plan")]

            drive(1.0)
            assert plans() and all(p.critic_costs["costmap"] == 0.0 for _, p in plans())
            rejected = hb()[-1].rejected
            grid_pub.put(encode(_wall_grid("map", time.time_ns())))  # not the states' frame
            drive(0.5)
            assert wait(lambda: hb()[-1].rejected > rejected, 15.0), hb()[-1]
            assert "grid in frame 'map', but the states are in 'odom'" in hb()[-1].last_error
            assert hb()[-1].counts.get("costmap_frame") == 1  # counted by name
            bad = json.loads(encode(_wall_grid("odom", time.time_ns())))
            bad["height"] = 7
            rejected = hb()[-1].rejected
            grid_pub.put(json.dumps(bad).encode())
            drive(0.5)
            assert wait(lambda: hb()[-1].rejected > rejected, 15.0), hb()[-1]
            t_grid, t_ns = time.monotonic(), time.time_ns()
            grid_pub.put(encode(_wall_grid("odom", time.time_ns())))
            drive(1.5)
            after = [p for t, p in plans() if t > t_grid + 0.5]
            assert after and any(p.critic_costs["costmap"] > 0.0 for p in after), [p.critic_costs for p in after]
            # the grid it plans among is published (so recorded and drawn), in the states' frame
            grids = [json.loads(p) for _, p, _ in col.on("gpmppi/r1/costmap")]  # ours among them, and the bad one
            assert any(g["header"]["frame_id"] == "odom" and g["header"]["stamp_ns"] > t_ns and g["width"] == 120
                       and sum(v >= 100 for v in g["data"]) == 160 for g in grids)
            assert planner.alive()
        finally:
            assert planner.stop() == 0, planner.log()[-3000:]


def test_a_new_grid_keeps_the_warm_start_and_is_prepared_between_states() -> None:
    from cached_models import synthetic_model

    from gpmppi.mppi.cycle import Planned, PlannerCycle
    from gpmppi.mppi.cycle_config import CycleConfig
    from gpmppi.mppi.planner import Planner, PlannerConfig
    from gpmppi.scenarios import paper_obstacle_scene

    scene = paper_obstacle_scene()
    planner = Planner(PlannerConfig(backend="cpu", samples=32, horizon=8), synthetic_model(nodes=4, n_train=20))
    cycle = PlannerCycle(planner, scene.task, CycleConfig(compensate_delay=False), 3)
    now = time.time_ns()
    assert isinstance(cycle.on_state(scene.start, now, time.monotonic(), now), Planned)
    grid = costmap_from_message(_wall_grid("odom", now))
    cycle.set_costmap(grid)
    assert cycle.task.costmap is grid and np.array_equal(cycle.task.obstacles, scene.task.obstacles)
    assert planner._iteration == 1  # not reset: the warm start stays
    assert "kernel" in grid._arrays  # its distance transform was built on arrival
    kind = planner.kind(cycle.task)
    assert kind._goal_scene is not None and grid.digest() in kind._goal_scene  # and its goal field
    out = cycle.on_state(scene.start, now + 100_000_000, time.monotonic(), now + 100_000_000)
    assert isinstance(out, Planned) and out.result.tightened.shape[1] == scene.task.obstacles.shape[0] + 1
    # a new goal task without a grid of its own plans among the cycle's grid
    cycle.set_task(type(scene.task)(goal=np.array([6.0, 6.0])))
    assert cycle.task.costmap is grid
    cycle.set_costmap(None)  # the grid withdrawn: the circles alone
    assert cycle.task.costmap is None
