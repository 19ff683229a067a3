"""ROS 2 navigation inputs -> our `Task`: a nav_msgs/Path is a lane to follow, a PoseStamped a goal to reach.

Free of Zenoh (the nav service is a thin shell over `NavTasks`), so each rule is tested on its own:

- a path is a lane: its centre line is the poses' positions in order, thinned to one every `spacing` metres (Nav2's
  come every 5 cm; the planner builds a lookup grid per lane whose cost grows with the segments, on the path of the
  first command after a swap), open (a path has an end), with the half-width and speed from the settings;
- a goal is a goal task with the settings' tolerance and the obstacles of the last goal task seen on `task` (the
  current scene), none if there was none;
- a path or goal whose `header.frame_id` is not the odometry's frame is refused, naming both frames: nothing here
  transforms between frames, and a plan in the wrong frame would drive the robot somewhere else;
- an empty path, a path of one position, one of more than `max_points` positions (after thinning), a non-finite
  position and malformed CDR are refused.

Every refusal is a `NavInputError` whose `name` is the heartbeat counter it is counted under.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas import Circle, Header, OccupancyGrid, Task
from services.codec import ros2

# the heartbeat counters of refused input, by name (each refusal is one of these)
REFUSALS = (
    "path_invalid", "path_frame", "path_empty", "path_short", "path_long", "path_nonfinite",
    "goal_invalid", "goal_frame", "goal_nonfinite", "costmap_invalid", "costmap_frame",
)


class NavInputError(ValueError):
    """A path or goal that is refused: `name` is its heartbeat counter (one of `REFUSALS`), the message says what
    was wrong and what to do."""

    def __init__(self, name: str, message: str) -> None:
        assert name in REFUSALS, name
        super().__init__(message)
        self.name = name


@dataclass(frozen=True)
class LaneFromPath:
    """How a path becomes a lane."""

    half_width: float  # [m]
    speed_target: float  # [m/s]
    spacing: float = 0.25  # keep a position only this far [m] from the last one kept (and always the last)
    max_points: int = 2000  # longer paths (after thinning) are refused


def thin(points: np.ndarray, spacing: float) -> np.ndarray:
    """The positions (P, 2) at least `spacing` [m] apart, walking from the first; the last is kept (replacing the last
    kept one when that is nearer than `spacing`, so the path still ends where it ended). Exact repeats are always
    dropped (a zero-length segment has no direction)."""
    kept = [0]
    for i in range(1, points.shape[0]):
        d = float(np.hypot(*(points[i] - points[kept[-1]])))
        if d > 0.0 and (d >= spacing or i == points.shape[0] - 1):
            kept.append(i)
    if len(kept) > 2 and float(np.hypot(*(points[kept[-1]] - points[kept[-2]]))) < spacing:
        del kept[-2]
    return points[kept]


def _check_frame(kind: str, frame_id: str, odom_frame: str) -> None:
    if frame_id != odom_frame:
        shown = repr(frame_id) if frame_id else "no frame (empty header.frame_id)"
        raise NavInputError(
            f"{kind}_frame",
            f"{kind} in frame {shown}, but odometry is in {odom_frame!r}: publish the {kind} in {odom_frame!r} "
            f"(Nav2: its global_frame), or set the nav service's frame_id to the odometry's frame",
        )


def lane_task_from_path(reading: ros2.PathReading, odom_frame: str, lane: LaneFromPath, stamp_ns: int) -> Task:
    """The lane task of a decoded path; raises NavInputError."""
    _check_frame("path", reading.frame_id, odom_frame)
    points = np.asarray(reading.points, dtype=np.float64).reshape(-1, 2)
    if points.shape[0] == 0:
        raise NavInputError("path_empty", "path has no poses: nothing to follow (kept the last task)")
    bad = np.nonzero(~np.all(np.isfinite(points), axis=1))[0]
    if bad.size:
        raise NavInputError("path_nonfinite", f"path pose {int(bad[0])} of {points.shape[0]} is not finite "
                            f"{points[bad[0]].tolist()} (kept the last task)")
    points = thin(points, lane.spacing)
    if points.shape[0] < 2:
        raise NavInputError("path_short", f"path has {points.shape[0]} distinct position; a lane needs 2 or more "
                            "(kept the last task)")
    if points.shape[0] > lane.max_points:
        raise NavInputError("path_long", f"path has {points.shape[0]} positions {lane.spacing} m apart, more than "
                            f"{lane.max_points}: send a shorter path (kept the last task)")
    return Task(
        header=Header(stamp_ns=stamp_ns, frame_id=odom_frame),
        kind="lane",
        centerline=points.tolist(),
        closed=False,
        half_width=lane.half_width,
        speed_target=lane.speed_target,
    )


def goal_task_from_pose(reading: ros2.PoseReading, odom_frame: str, tolerance: float, obstacles: list[Circle],
                        stamp_ns: int) -> Task:
    """The goal task of a decoded goal pose among `obstacles`; raises NavInputError."""
    _check_frame("goal", reading.frame_id, odom_frame)
    position = np.asarray(reading.position, dtype=np.float64).reshape(2)
    if not np.all(np.isfinite(position)):
        raise NavInputError("goal_nonfinite", f"goal position {position.tolist()} is not finite (kept the last task)")
    return Task(
        header=Header(stamp_ns=stamp_ns, frame_id=odom_frame),
        kind="goal",
        goal=position.tolist(),
        goal_tolerance=tolerance,
        obstacles=list(obstacles),
    )


class NavTasks:
    """The nav service's state: the odometry frame, how paths become lanes, and the current scene's obstacles."""

    def __init__(self, odom_frame: str, lane: LaneFromPath, goal_tolerance: float) -> None:
        self.odom_frame = odom_frame
        self.lane = lane
        self.goal_tolerance = goal_tolerance
        self.obstacles: list[Circle] = []  # of the last goal task seen on `task` (the scene a goal is reached in)

    def on_task(self, task: Task) -> None:
        """A task seen on `task` (the planner re-publishes the one it plans for): a goal task's obstacles are the
        scene the next goal is given in. A task with no goal (a lane) has no scene and leaves it as it is."""
        if task.goal is not None:
            self.obstacles = list(task.obstacles)

    def from_path(self, data: bytes, stamp_ns: int, distro: ros2.Distro = "jazzy") -> Task:
        """The lane task of nav_msgs/Path CDR bytes; raises NavInputError."""
        try:
            reading = ros2.path_from_cdr(data, distro)
        except ValueError as exc:
            raise NavInputError("path_invalid", str(exc)) from exc
        return lane_task_from_path(reading, self.odom_frame, self.lane, stamp_ns)

    def from_goal(self, data: bytes, stamp_ns: int, distro: ros2.Distro = "jazzy") -> Task:
        """The goal task of geometry_msgs/PoseStamped CDR bytes among the scene's obstacles; raises
        NavInputError. The goal task is the scene from now on."""
        try:
            reading = ros2.pose_stamped_from_cdr(data, distro)
        except ValueError as exc:
            raise NavInputError("goal_invalid", str(exc)) from exc
        task = goal_task_from_pose(reading, self.odom_frame, self.goal_tolerance, self.obstacles, stamp_ns)
        self.on_task(task)
        return task

    def from_costmap(self, data: bytes, stamp_ns: int, distro: ros2.Distro = "jazzy",
                     lethal: int = 100) -> OccupancyGrid:
        """Our grid of nav_msgs/OccupancyGrid CDR bytes (Nav2's costmap: 100 lethal); raises NavInputError for a
        grid that is malformed (its size not its data's, a bad origin) or in a frame other than the odometry's.
        `stamp_ns` is unused: a grid keeps its own stamp (its age is the sensor's)."""
        try:
            grid = ros2.occupancy_grid_from_cdr(data, distro, lethal)
        except ValueError as exc:
            raise NavInputError("costmap_invalid", f"{exc} (kept the last grid)") from exc
        _check_frame("costmap", grid.header.frame_id, self.odom_frame)
        return grid
