"""ROS 2 paths and goals into tasks, without Zenoh: rosbags-made nav_msgs/Path and geometry_msgs/PoseStamped CDR
(both distros) become the lane and goal tasks the planner takes; bad input is refused by name, naming both frames
when the frame is wrong; the planner's plan goes out as a nav_msgs/Path that rosbags decodes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from gpmppi.scenarios import load_lane, shipped_lane_files
from gpmppi.tasks import distance_to_polyline
from schemas import Circle, Task
from services.codec import ros2
from services.codec.convert import task_from_message
from services.codec.nav_tasks import REFUSALS, LaneFromPath, NavInputError, NavTasks
from services.planner import Settings
from services.planner_outputs import Ros2PlanOutput

STORES = {"jazzy": get_typestore(Stores.ROS2_JAZZY), "humble": get_typestore(Stores.ROS2_HUMBLE)}
STAMP = 1_700_000_000 * 10**9 + 250


def _header(ts, frame_id: str, stamp_ns: int = STAMP):  # noqa: ANN001, ANN202 - rosbags' generated types
    t = ts.types
    return t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=frame_id
    )


def _pose(ts, x: float, y: float, yaw: float, frame_id: str):  # noqa: ANN001, ANN202
    t = ts.types
    return t["geometry_msgs/msg/PoseStamped"](
        header=_header(ts, frame_id),
        pose=t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
        ),
    )


def path_cdr(points: np.ndarray, frame_id: str = "odom", distro: str = "jazzy") -> bytes:
    """A nav_msgs/Path through `points` (P, 2), made with rosbags alone (as a ROS 2 node would send it)."""
    ts = STORES[distro]
    poses = [_pose(ts, float(x), float(y), 0.0, frame_id) for x, y in np.asarray(points).reshape(-1, 2)]
    msg = ts.types["nav_msgs/msg/Path"](header=_header(ts, frame_id), poses=poses)
    return bytes(ts.serialize_cdr(msg, "nav_msgs/msg/Path"))


def goal_cdr(x: float, y: float, frame_id: str = "odom", distro: str = "jazzy") -> bytes:
    ts = STORES[distro]
    return bytes(ts.serialize_cdr(_pose(ts, x, y, 0.5, frame_id), "geometry_msgs/msg/PoseStamped"))


def _nav() -> NavTasks:
    return NavTasks("odom", LaneFromPath(half_width=2.0, speed_target=1.5), goal_tolerance=0.4)


def _refusal(call, *args) -> NavInputError:  # noqa: ANN001
    with pytest.raises(NavInputError) as info:
        call(*args)
    assert info.value.name in REFUSALS
    return info.value


@pytest.mark.parametrize("distro", ["jazzy", "humble"])
def test_a_path_is_an_open_lane_and_a_goal_keeps_the_scene(distro: str) -> None:
    oval = load_lane(next(p for p in shipped_lane_files() if p.name == "lane_oval.yaml")).task
    nav = _nav()
    # a planner's path often starts with the robot's position twice: the repeat is dropped (no zero-length segment)
    points = np.vstack([oval.centerline[:1], oval.centerline])
    msg = nav.from_path(path_cdr(points, distro=distro), 5, distro)
    assert (msg.kind, msg.closed, msg.half_width, msg.speed_target) == ("lane", False, 2.0, 1.5)
    assert msg.header.stamp_ns == 5 and msg.header.frame_id == "odom"
    lane = task_from_message(Task.model_validate(msg.model_dump()))
    np.testing.assert_array_equal(lane.centerline, oval.centerline)
    assert not lane.closed
    # a goal with no scene yet: no obstacles
    goal = nav.from_goal(goal_cdr(3.0, -1.5, distro=distro), 6, distro)
    assert (goal.kind, goal.goal, goal.goal_tolerance, goal.obstacles) == ("goal", [3.0, -1.5], 0.4, [])
    # the planner's current scene (a goal task among circles) is kept for the next goal, and a lane in between does
    # not clear it
    scene = [Circle(x=1.0, y=1.0, r=0.5), Circle(x=2.0, y=-3.0, r=0.25)]
    nav.on_task(Task(kind="goal", goal=[9.0, 9.0], obstacles=scene))
    nav.on_task(msg)
    goal = nav.from_goal(goal_cdr(4.0, 0.0, distro=distro), 7, distro)
    assert goal.goal == [4.0, 0.0] and goal.obstacles == scene


def test_a_dense_path_is_thinned_to_the_spacing_and_keeps_its_ends() -> None:
    # Nav2's planner: a pose every 5 cm, here along a quarter circle of radius 3 m, and its first pose twice
    a = np.linspace(0.0, np.pi / 2, 95)
    arc = np.column_stack([3.0 * np.cos(a), 3.0 * np.sin(a)])
    dense = np.vstack([arc[:1], arc])
    lane = task_from_message(_nav().from_path(path_cdr(dense), 0))
    c = lane.centerline
    steps = np.hypot(*np.diff(c, axis=0).T)
    assert c.shape[0] < dense.shape[0] / 4 and np.all(steps >= 0.25 - 1e-9) and np.all(steps < 0.5)
    np.testing.assert_array_equal(c[0], arc[0])
    np.testing.assert_array_equal(c[-1], arc[-1])
    # the thinned polyline stays within a centimetre of the circle (its longest chord, the last: 0.45^2 / (8 * 3) m)
    assert distance_to_polyline(arc, c, closed=False).max() < 0.01
    # spacing 0 keeps every distinct position (the repeat still goes)
    every = NavTasks("odom", LaneFromPath(1.0, 1.0, spacing=0.0), 0.5).from_path(path_cdr(dense), 0)
    assert len(every.centerline) == arc.shape[0]


def test_bad_paths_and_goals_are_refused_by_name() -> None:
    nav = _nav()
    line = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    wrong = _refusal(nav.from_path, path_cdr(line, frame_id="map"), 0)
    assert wrong.name == "path_frame" and "'map'" in str(wrong) and "'odom'" in str(wrong)
    assert _refusal(nav.from_path, path_cdr(line, frame_id=""), 0).name == "path_frame"
    assert _refusal(nav.from_path, path_cdr(np.zeros((0, 2))), 0).name == "path_empty"
    assert _refusal(nav.from_path, path_cdr(np.array([[1.0, 2.0], [1.0, 2.0]])), 0).name == "path_short"
    nan = line.copy()
    nan[1, 1] = np.nan
    refused = _refusal(nav.from_path, path_cdr(nan), 0)
    assert refused.name == "path_nonfinite" and "pose 1 of 3" in str(refused)
    inf = line.copy()
    inf[2, 0] = np.inf
    assert _refusal(nav.from_path, path_cdr(inf), 0).name == "path_nonfinite"
    long = _refusal(NavTasks("odom", LaneFromPath(1.0, 1.0, max_points=2), 0.5).from_path, path_cdr(line), 0)
    assert long.name == "path_long" and "3 positions" in str(long)
    assert _refusal(nav.from_path, b"\x00\x01\x00\x00junk", 0).name == "path_invalid"
    # a goal on the path key is no path either
    assert _refusal(nav.from_path, goal_cdr(1.0, 1.0), 0).name == "path_invalid"
    wrong = _refusal(nav.from_goal, goal_cdr(1.0, 1.0, frame_id="map"), 0)
    assert wrong.name == "goal_frame" and "'map'" in str(wrong) and "'odom'" in str(wrong)
    assert _refusal(nav.from_goal, goal_cdr(np.nan, 1.0), 0).name == "goal_nonfinite"
    assert _refusal(nav.from_goal, b"\x00\x01", 0).name == "goal_invalid"


def test_the_plan_goes_out_as_a_path_rosbags_decodes() -> None:
    states = np.array([[0.0, 0.0, 0.1, 1.0, 0.0], [0.1, 0.01, 0.2, 1.0, 0.0], [0.2, 0.03, -3.0, 1.0, 0.0]])
    stamps = STAMP + np.arange(3) * 100_000_000
    for distro, ts in STORES.items():
        data = ros2.path_cdr(states[:, :3], stamps, "odom", int(stamps[0]), distro)  # type: ignore[arg-type]
        msg = ts.deserialize_cdr(data, "nav_msgs/msg/Path")
        assert msg.header.frame_id == "odom" and len(msg.poses) == 3
        for pose, s, stamp in zip(msg.poses, states, stamps, strict=True):
            assert pose.header.frame_id == "odom"
            assert pose.header.stamp.sec * 10**9 + pose.header.stamp.nanosec == stamp
            p, q = pose.pose.position, pose.pose.orientation
            assert (p.x, p.y) == (s[0], s[1])
            assert math.atan2(2 * q.w * q.z, 1 - 2 * q.z * q.z) == pytest.approx(s[2], abs=1e-12)
    # the plan's topic, on both key forms
    plan = Settings(ros2_plan={"enabled": True, "namespace": "/jackal"}).ros2_plan
    assert plan.key_expr("nav_msgs/msg/Path") == (
        "0/jackal/local_plan/nav_msgs::msg::dds_::Path_/" + STORES["jazzy"].hash_rihs01("nav_msgs/msg/Path"))
    bridge = Ros2PlanOutput(enabled=True, topic="gp_plan", key_style="bridge")
    assert bridge.key_expr("nav_msgs/msg/Path") == "gp_plan"


@pytest.mark.parametrize("distro", ["jazzy", "humble"])
def test_a_nav2_costmap_becomes_our_grid_and_bad_ones_are_refused_by_name(distro: str) -> None:
    from schemas import OccupancyGrid

    nav = NavTasks("odom", LaneFromPath(1.0, 1.0, 0.25, 2000), 0.5)
    values = np.zeros((20, 30), dtype=np.int8)
    values[5:8, 10:12] = 100
    good = ros2.occupancy_grid_cdr(values, 0.1, (1.0, -2.0, 0.0), 7 * 10**9, frame_id="odom", distro=distro)
    grid = nav.from_costmap(good, 0, distro=distro, lethal=99)
    assert isinstance(grid, OccupancyGrid) and (grid.width, grid.height, grid.lethal) == (30, 20, 99)
    assert grid.header.stamp_ns == 7 * 10**9 and sum(v >= 99 for v in grid.data) == 6
    wrong_frame = ros2.occupancy_grid_cdr(values, 0.1, (0.0, 0.0, 0.0), 1, frame_id="map", distro=distro)
    with pytest.raises(NavInputError) as exc:
        nav.from_costmap(wrong_frame, 0, distro=distro)
    assert exc.value.name == "costmap_frame" and "'map'" in str(exc.value) and "'odom'" in str(exc.value)
    mismatched = ros2.occupancy_grid_cdr(values, 0.1, (0.0, 0.0, 0.0), 1, frame_id="odom", distro=distro, width=31)
    with pytest.raises(NavInputError) as exc:
        nav.from_costmap(mismatched, 0, distro=distro)
    assert exc.value.name == "costmap_invalid" and "size must match" in str(exc.value)
    assert {"costmap_frame", "costmap_invalid"} <= set(REFUSALS)
