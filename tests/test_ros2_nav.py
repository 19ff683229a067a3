"""gpmppi as the local controller under Nav2: rosbags-made nav_msgs/Path and geometry_msgs/PoseStamped on both key
forms (rmw_zenoh jazzy with its attachment, zenoh-bridge-ros2dds humble) to a running stack over loopback Zenoh; the
robot waits for a task, follows a path, drives on through a path swap and through bad input, takes Nav2's costmap
(refusing one in the wrong frame), reaches a goal around the costmap's block, and the
plan comes out as a nav_msgs/Path rosbags decodes. And, in process through the same conversion, a path made from the
shipped oval tracks as well as the oval lane file."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from test_nav_tasks import STORES, goal_cdr, path_cdr
from zenoh_helpers import Collector, ServiceProcess, client, free_port, heartbeats, router, settings, wait_for

from gpmppi.evaluation.closed_loop import ClosedLoopConfig, run_closed_loop
from gpmppi.evaluation.metrics import lane_rmse_mm
from gpmppi.evaluation.runner import EvalSettings, cached_gp_model, make_planner, make_plant
from gpmppi.scenarios import load_lane, shipped_lane_files
from schemas import BaseCommand, Command, OccupancyGrid, State, Task, decode
from services.codec import ros2
from services.codec.convert import task_from_message
from services.codec.nav_tasks import LaneFromPath, NavTasks

ROBOT = "r1"
JAZZY = STORES["jazzy"]
PATH_KEY = "0/plan/nav_msgs::msg::dds_::Path_/" + JAZZY.hash_rihs01("nav_msgs/msg/Path")
GOAL_KEY = "0/goal_pose/geometry_msgs::msg::dds_::PoseStamped_/" + JAZZY.hash_rihs01("geometry_msgs/msg/PoseStamped")
PLAN_KEY = "0/local_plan/nav_msgs::msg::dds_::Path_/" + JAZZY.hash_rihs01("nav_msgs/msg/Path")
BRIDGE_PATH, BRIDGE_GOAL = "robot/plan", "robot/goal_pose"  # zenoh-bridge-ros2dds keys (namespace /robot)
GRID_KEY = ("0/local_costmap/costmap/nav_msgs::msg::dds_::OccupancyGrid_/"
            + JAZZY.hash_rihs01("nav_msgs/msg/OccupancyGrid"))
BRIDGE_GRID = "robot/local_costmap/costmap"


def test_a_path_made_from_the_oval_tracks_like_the_oval_lane() -> None:
    """In process (the closed loop over the deployed command path), the oval lane file against the open path made
    from its centre line through the nav conversion, same seeds: lane RMSE within 1.2x."""
    oval = load_lane(next(p for p in shipped_lane_files() if p.name == "lane_oval.yaml"))
    nav = NavTasks("odom", LaneFromPath(oval.task.half_width, oval.task.speed_target), goal_tolerance=0.5)
    from_path = task_from_message(nav.from_path(path_cdr(oval.task.centerline), 0))
    assert not from_path.closed and oval.task.closed
    evaluation = EvalSettings(samples=256)
    rmse: dict[bool, list[float]] = {True: [], False: []}
    for seed in range(2):
        for task in (oval.task, from_path):
            traj = run_closed_loop(make_planner(evaluation, "gp", "asphalt", seed),
                                   make_plant(evaluation, "asphalt", seed), task, oval.start,
                                   cached_gp_model(None).n_terrains, ClosedLoopConfig(time_limit_s=30.0),
                                   initial_terrain="asphalt")
            assert traj.measured_states.shape[0] > 250  # it drove the 30 s, not off the path's end
            rmse[task.closed].append(lane_rmse_mm(traj.measured_states[:, :2], oval.task.centerline, closed=True))
    assert np.mean(rmse[False]) <= 1.2 * np.mean(rmse[True]), rmse


def _nav_config(port: int, service: str, key_style: str, distro: str, namespace: str = "") -> dict:
    topic = {"key_style": key_style, "distro": distro, "namespace": namespace}
    return settings(service, port, ROBOT, heartbeat_hz=5.0, frame_id="odom", half_width=1.5, speed_target=1.25,
                    goal_tolerance=0.4, path={"topic": "plan", **topic}, goal={"topic": "goal_pose", **topic},
                    costmap={"topic": "local_costmap/costmap", **topic})


def _attachment(seq: int) -> bytes:
    return ros2.Attachment(seq, time.time_ns(), ros2.new_gid(7)).to_bytes()


@pytest.mark.slow(seconds=15)
def test_paths_and_goals_from_ros2_drive_a_running_stack(tmp_path: Path) -> None:
    port = free_port()
    configs = {
        "sim": settings("sim", port, ROBOT, start=[0.0, 0.0, 0.0, 0.0, 0.0], noise=False),
        "ingress": settings("ingress", port, ROBOT, source="sim"),
        "planner": settings("planner", port, ROBOT, scenario="none", trigger="state", heartbeat_hz=5.0,
                            planner={"samples": 256}, ros2_plan={"enabled": True, "gid_seed": 1}),
        # a watchdog of 0.5 s, not 0.25: a planner that stops commanding still shows as zero, a loaded machine's
        # scheduling gap does not
        "egress": settings("egress", port, ROBOT, output="sim", watchdog_timeout_s=0.5),
        "nav": _nav_config(port, "nav", "rmw_zenoh", "jazzy"),
        "nav_bridge": _nav_config(port, "nav_bridge", "bridge", "humble", "/robot"),
    }
    with router(port):
        s = client(port)
        col = Collector(s, "gpmppi/**")
        plans = Collector(s, PLAN_KEY)
        procs: dict[str, ServiceProcess] = {}
        try:
            for name, cfg in configs.items():
                (tmp_path / name).mkdir()
                procs[name] = ServiceProcess("nav" if name.startswith("nav") else name, cfg, tmp_path / name)
            for name, proc in procs.items():  # the planner loads its kernels from the cache (a cold one compiles)
                up = wait_for(lambda n=name: bool(heartbeats(col, ROBOT, n)) or not procs[n].alive(), 600.0, 0.1)
                assert up and proc.alive(), f"{name} did not come up:\n{proc.log()[-3000:]}"
            _drive(s, col, plans)
        finally:
            codes = {name: p.stop() for name, p in reversed(procs.items())}
            s.close()
    assert all(c == 0 for c in codes.values()), codes


def _states(col: Collector) -> list[tuple[float, State]]:
    return [(t, decode(State, p)) for t, p, _ in col.on(f"gpmppi/{ROBOT}/state")]


def _commands(col: Collector, since: float) -> list[tuple[float, Command]]:
    return [(t, decode(Command, p)) for t, p, _ in col.on(f"gpmppi/{ROBOT}/cmd") if t >= since]


def _hb_counts(col: Collector, service: str) -> dict[str, int]:
    hbs = heartbeats(col, ROBOT, service)
    return hbs[-1].counts if hbs else {}


def _drive(s: zenoh.Session, col: Collector, plans: Collector) -> None:
    rmw_path = s.declare_publisher(PATH_KEY, encoding=zenoh.Encoding("application/cdr"))
    rmw_goal = s.declare_publisher(GOAL_KEY, encoding=zenoh.Encoding("application/cdr"))
    bridge_path, bridge_goal = s.declare_publisher(BRIDGE_PATH), s.declare_publisher(BRIDGE_GOAL)
    for pub in (rmw_path, rmw_goal, bridge_path, bridge_goal):
        assert wait_for(lambda p=pub: p.matching_status.matching, 15.0)

    # no task yet: the planner plans nothing, so egress holds the robot at zero
    time.sleep(1.0)
    assert _commands(col, 0.0) == [] and _hb_counts(col, "planner").get("no_task", 0) > 0

    # bad input: each refused and counted by name, no task published, the robot still waits
    line = np.column_stack([np.linspace(0.0, 40.0, 81), np.zeros(81)])
    nan = line.copy()
    nan[3, 1] = np.nan
    bad = [(rmw_path, path_cdr(np.zeros((0, 2)))), (rmw_path, path_cdr(nan)),
           (rmw_path, path_cdr(line, frame_id="map")), (rmw_goal, goal_cdr(3.0, 0.0, frame_id="map")),
           (rmw_goal, goal_cdr(np.nan, 0.0))]
    for seq, (pub, payload) in enumerate(bad, start=1):
        pub.put(payload, attachment=_attachment(seq))
        # one at a time: the newest path (and goal) replaces one not yet taken
        assert wait_for(lambda n=seq: sum(_hb_counts(col, "nav").values()) == n, 5.0), _hb_counts(col, "nav")
    wanted = {"path_empty": 1, "path_nonfinite": 1, "path_frame": 1, "goal_frame": 1, "goal_nonfinite": 1}
    assert wait_for(lambda: _hb_counts(col, "nav") == wanted, 5.0), _hb_counts(col, "nav")
    assert heartbeats(col, ROBOT, "nav")[-1].rejected == 5
    assert col.on(f"gpmppi/{ROBOT}/task") == [] and _commands(col, 0.0) == []

    # a path on the rmw_zenoh key: the robot follows it
    rmw_path.put(path_cdr(line), attachment=_attachment(10))
    assert wait_for(lambda: any(s.x > 2.0 for _, s in _states(col)), 20.0), "the robot did not drive the path"
    tasks = [decode(Task, p) for _, p, _ in col.on(f"gpmppi/{ROBOT}/task")]
    assert tasks[0].kind == "lane" and not tasks[0].closed and tasks[0].half_width == 1.5

    # a new path (humble, bridge key) while driving: the commands go on, none zero, no gap beyond two cycles (with
    # the warm start forgotten at the swap, as before, v_ref fell to 0.2 m/s here)
    swap_at = time.monotonic()
    x0 = _states(col)[-1][1].x
    # as Nav2's planner sends it: a pose every 5 cm (thinned to 25 cm by the nav service)
    s_new = np.arange(0.0, 30.0, 0.05)
    curve = np.column_stack([x0 + s_new, 0.6 * np.sin(s_new / 10.0)])
    bridge_path.put(path_cdr(curve, distro="humble"))
    # and bad input while driving: refused, the robot drives on the last good path
    time.sleep(1.0)
    rmw_path.put(path_cdr(nan), attachment=_attachment(11))
    time.sleep(1.5)
    assert _hb_counts(col, "nav_bridge") == {} and _hb_counts(col, "nav").get("path_nonfinite") == 2
    task_times = [t for t, p, _ in col.on(f"gpmppi/{ROBOT}/task")
                  if decode(Task, p).centerline[-1] == pytest.approx(curve[-1].tolist())]
    assert task_times and task_times[0] - swap_at < 1.5, "the planner did not take the new path"
    window = _commands(col, swap_at - 0.5)
    # every state is answered (the command carries its state's stamp), or at most two in a row are skipped (the
    # first plan on the new path builds its lane lookup: 40-60 ms alone, longer on a loaded machine): counted in
    # planner cycles, not wall-clock gaps, which that load stretches
    answered = {c.header.stamp_ns for _, c in window}
    around = [(t - swap_at, st.header.stamp_ns) for t, st in _states(col) if swap_at - 0.4 <= t <= swap_at + 2.0]
    pattern = "".join("." if stamp in answered else "x" for _, stamp in around)  # x: a state with no command
    in_a_row = max(len(run) for run in pattern.split("."))
    assert len(around) > 15 and in_a_row <= 2, (pattern, [round(t, 2) for t, _ in around])
    assert min(c.v_ref for _, c in window) > 0.3, [round(c.v_ref, 2) for _, c in window]
    base = [decode(BaseCommand, p) for t, p, _ in col.on(f"gpmppi/{ROBOT}/base/cmd") if t >= swap_at - 0.5]
    assert all(b.reason != "watchdog" and b.v > 0.3 for b in base), [(b.reason, round(b.v, 2)) for b in base]

    # the plan out: nav_msgs/Path in the odometry's frame, a pose a step, stamped 0.1 s apart, with attachments
    _, payload, attachment = plans.on(PLAN_KEY)[-1]
    plan = JAZZY.deserialize_cdr(payload, "nav_msgs/msg/Path")
    stamps = np.array([p.header.stamp.sec * 10**9 + p.header.stamp.nanosec for p in plan.poses])
    assert plan.header.frame_id == "odom" and len(plan.poses) == 41
    assert np.allclose(np.diff(stamps), 1e8, atol=1)
    assert ros2.Attachment.from_bytes(attachment).sequence_number == len(plans.on(PLAN_KEY))
    robot = _states(col)[-1][1]
    assert abs(plan.poses[0].pose.position.x - robot.x) < 1.0 and plan.poses[-1].pose.position.x > robot.x + 2.0

    # a costmap (Nav2's local costmap) with a 0.6 m block halfway to the goal below: one in the wrong frame on the
    # rmw_zenoh key is refused by name; the good one (humble, bridge key) reaches the planner, which plans the goal
    # among it
    goal = np.array([robot.x + 3.0, robot.y + 2.0])
    block = (np.array([robot.x, robot.y]) + goal) / 2
    res, origin = 0.05, (robot.x - 2.0, robot.y - 3.0, 0.0)
    values = np.zeros((160, 160), dtype=np.int8)
    col_, row_ = ((block - np.array(origin[:2])) / res).astype(int)
    values[row_ - 6:row_ + 6, col_ - 6:col_ + 6] = 100
    rmw_grid = s.declare_publisher(GRID_KEY, encoding=zenoh.Encoding("application/cdr"))
    bridge_grid = s.declare_publisher(BRIDGE_GRID)
    for pub in (rmw_grid, bridge_grid):
        assert wait_for(lambda p=pub: p.matching_status.matching, 15.0)
    rmw_grid.put(ros2.occupancy_grid_cdr(values, res, origin, time.time_ns(), frame_id="map"),
                 attachment=_attachment(12))
    assert wait_for(lambda: _hb_counts(col, "nav").get("costmap_frame") == 1, 5.0), _hb_counts(col, "nav")
    bridge_grid.put(ros2.occupancy_grid_cdr(values, res, origin, time.time_ns(), frame_id="odom", distro="humble"))
    assert wait_for(lambda: any(decode(OccupancyGrid, p).width == 160
                                for _, p, _ in col.on(f"gpmppi/{ROBOT}/costmap")), 5.0), "no grid forwarded"

    # a goal (humble, bridge key) 3 m to the side ahead, the block on the straight line to it: reached around it
    sent = time.monotonic()
    bridge_goal.put(goal_cdr(float(goal[0]), float(goal[1]), distro="humble"))
    reached = wait_for(lambda: np.hypot(*(np.array([_states(col)[-1][1].x, _states(col)[-1][1].y]) - goal)) < 0.4,
                       15.0)
    last = _states(col)[-1][1]
    assert reached, f"goal {goal.tolist()} not reached: robot at {[last.x, last.y]}"
    driven = np.array([[st.x, st.y] for t, st in _states(col) if t >= sent])
    assert np.all(np.max(np.abs(driven - block), axis=1) > 0.3), "the robot drove through the costmap's block"
    assert decode(Task, col.on(f"gpmppi/{ROBOT}/task")[-1][1]).kind == "goal"
