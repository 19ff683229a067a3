"""nav: ROS 2 navigation inputs -> `Task` on `gpmppi/{robot}/task`, so gpmppi runs as the local controller under Nav2.

A `nav_msgs/msg/Path` (Nav2's planner, `plan`) becomes a lane task and a `geometry_msgs/msg/PoseStamped` (RViz's
and Nav2's goal, `goal_pose`) a goal task, both as CDR over Zenoh on the rmw_zenoh key (any type hash, so jazzy's
and humble's publishers both match) or the zenoh-bridge-ros2dds key. The planner, recorder and viewer see the
`Task` like any other. A new path replaces the last at the planner without stopping the robot. A
`nav_msgs/msg/OccupancyGrid` (Nav2's local costmap, `local_costmap/costmap`) goes to the planner as our
`OccupancyGrid` on `costmap`: goal tasks plan among it (the planner drops a grid that stops coming:
`max_costmap_age_s`).

Bad input (malformed CDR, an empty path, a non-finite position, a frame other than the odometry's) is refused,
counted by name in the heartbeat (`services.codec.nav_tasks.REFUSALS`) and logged; the planner drives on the last
good task (or, with none, plans nothing: egress's watchdog holds the robot at zero). The conversion is
`services.codec.nav_tasks`; this module only receives, converts and publishes.
"""

from __future__ import annotations

import time
from functools import partial

from pydantic import Field

from schemas import OccupancyGrid, Task
from services.codec.nav_tasks import LaneFromPath, NavInputError, NavTasks
from services.codec.ros2_topic import Ros2Topic
from services.runtime.node import Node
from services.runtime.node_settings import NodeSettings

PATH_TYPE = "nav_msgs/msg/Path"
GOAL_TYPE = "geometry_msgs/msg/PoseStamped"
GRID_TYPE = "nav_msgs/msg/OccupancyGrid"


class Settings(NodeSettings):
    service: str = Field("nav", description="service name")
    frame_id: str = Field(
        "odom", min_length=1,
        description="the odometry's frame (ingress's State frame): paths and goals in another frame are refused",
    )
    path: Ros2Topic = Field(default_factory=lambda: Ros2Topic(topic="plan"),
                            description="the nav_msgs/Path topic (Nav2's planner publishes `plan`)")
    goal: Ros2Topic = Field(default_factory=lambda: Ros2Topic(topic="goal_pose"),
                            description="the geometry_msgs/PoseStamped goal topic (RViz's `2D Goal Pose`: `goal_pose`)")
    costmap: Ros2Topic = Field(
        default_factory=lambda: Ros2Topic(topic="local_costmap/costmap"),
        description="the nav_msgs/OccupancyGrid topic (Nav2's local costmap: `local_costmap/costmap`), published to "
        "the planner as our OccupancyGrid on `costmap`; it must be in the odometry's frame (a rolling local costmap "
        "in `odom`)")
    costmap_lethal: int = Field(100, ge=1, le=127, description="grid values >= this are obstacles (Nav2's costmap "
                                "topic: 100 lethal, 99 inscribed)")
    half_width: float = Field(1.0, gt=0, description="half-width of the lane a path becomes [m]")
    speed_target: float = Field(1.0, ge=0, description="speed along a path [m/s]")
    path_spacing: float = Field(
        0.25, ge=0, description="a path's positions are thinned to this spacing [m]: the planner's lane lookup costs "
        "time per segment on the first command after a swap (0: keep every distinct position)"
    )
    max_path_points: int = Field(2000, ge=2, description="paths with more positions (after thinning) are refused")
    goal_tolerance: float = Field(0.5, gt=0, description="a goal is reached within this distance [m]")


def run(settings: Settings) -> int:
    with Node(settings) as node:
        return serve(node, settings)


def serve(node: Node, settings: Settings) -> int:
    """The nav service's loop on an open node, until it is stopped."""
    lane = LaneFromPath(settings.half_width, settings.speed_target, settings.path_spacing, settings.max_path_points)
    nav = NavTasks(settings.frame_id, lane, settings.goal_tolerance)
    out = node.publisher("task")
    grids = node.publisher("costmap")
    scene = node.subscribe("task", remote_only=True)  # what the planner plans for (it re-publishes it)
    path_key, goal_key = settings.path.key_expr(PATH_TYPE, subscribe=True), settings.goal.key_expr(GOAL_TYPE, True)
    inputs = [  # newest only: a path replaces the one before it
        (node.inbox(path_key), partial(nav.from_path, distro=settings.path.distro)),
        (node.inbox(goal_key), partial(nav.from_goal, distro=settings.goal.distro)),
        (node.inbox(settings.costmap.key_expr(GRID_TYPE, subscribe=True)),
         partial(nav.from_costmap, distro=settings.costmap.distro, lethal=settings.costmap_lethal)),
    ]
    node.log.info("paths from %s, goals from %s, costmaps from %s, frame %s",
                  settings.path.key_expr(PATH_TYPE, subscribe=True), settings.goal.key_expr(GOAL_TYPE, subscribe=True),
                  settings.costmap.key_expr(GRID_TYPE, subscribe=True), settings.frame_id)
    while node.ok():
        if (current := scene.take()) is not None:
            nav.on_task(current)
        for inbox, convert in inputs:
            if (sample := inbox.take()) is None:
                continue
            node.counters.received += 1
            try:
                msg: Task | OccupancyGrid = convert(sample.payload.to_bytes(), time.time_ns())
            except NavInputError as exc:
                node.counters.count(exc.name)
                node.reject(f"{sample.key_expr}: {exc}")
                continue
            if isinstance(msg, OccupancyGrid):
                grids.put(msg)
            else:
                out.put(msg)
                node.log.info("new %s task from %s", msg.kind, sample.key_expr)
            node.cycle()
        node.spin_once()
    return 0
