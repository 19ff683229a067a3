"""Messages <-> the core's arrays and tasks (one place, so every service converts the same way)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from gpmppi.costmap import Costmap
from gpmppi.tasks import GoalTask, LaneTask
from gpmppi.tasks import Task as CoreTask
from schemas import Circle, Header, OccupancyGrid, State, Task


def now_ns() -> int:
    return time.time_ns()


def wrap_angle(a: float) -> float:
    """Angle wrapped to (-pi, pi]."""
    w = math.remainder(a, 2.0 * math.pi)
    return math.pi if w == -math.pi else w


def state_to_array(msg: State) -> np.ndarray:
    return np.array([msg.x, msg.y, msg.theta, msg.v, msg.omega], dtype=np.float64)


def state_from_array(
    x: np.ndarray, stamp_ns: int, frame_id: str = "map", covariance: np.ndarray | None = None
) -> State:
    """A State message from [X, Y, theta, v, omega]; raises ValueError on non-finite input."""
    values = [float(v) for v in np.asarray(x, dtype=np.float64).reshape(5)]
    cov = None if covariance is None else [float(v) for v in np.asarray(covariance, dtype=np.float64).reshape(25)]
    return State(
        header=Header(stamp_ns=stamp_ns, frame_id=frame_id),
        x=values[0],
        y=values[1],
        theta=wrap_angle(values[2]),
        v=values[3],
        omega=values[4],
        covariance=cov,
    )


@dataclass(frozen=True)
class TaskCodec:
    """A task kind's message conversion: `to_message(task, header)` and `from_message(msg)` (`schemas.Task` fields)."""

    to_message: Callable[[CoreTask, Header], Task]
    from_message: Callable[[Task], CoreTask]


def _lane_to_message(task: LaneTask, header: Header) -> Task:
    return Task(header=header, kind="lane", centerline=[[float(p[0]), float(p[1])] for p in task.centerline],
                closed=task.closed, half_width=task.half_width, speed_target=task.speed_target)


def _lane_from_message(msg: Task) -> LaneTask:
    return LaneTask(np.asarray(msg.centerline, dtype=np.float64), half_width=msg.half_width,
                    speed_target=msg.speed_target, closed=msg.closed)


def _goal_to_message(task: GoalTask, header: Header) -> Task:
    return Task(header=header, kind="goal", goal=[float(task.goal[0]), float(task.goal[1])],
                goal_tolerance=task.tolerance,
                obstacles=[Circle(x=float(o[0]), y=float(o[1]), r=float(o[2])) for o in task.obstacles])


def _goal_from_message(msg: Task) -> GoalTask:
    obstacles = np.array([[o.x, o.y, o.r] for o in msg.obstacles], dtype=np.float64).reshape(-1, 3)
    return GoalTask(goal=np.asarray(msg.goal, dtype=np.float64), tolerance=msg.goal_tolerance, obstacles=obstacles)


# by the kind's name (the task type's `kind`, the message's `kind`); a new kind adds its codec here
TASK_CODECS: dict[str, TaskCodec] = {
    LaneTask.kind: TaskCodec(_lane_to_message, _lane_from_message),
    GoalTask.kind: TaskCodec(_goal_to_message, _goal_from_message),
}


def _codec(kind: str) -> TaskCodec:
    codec = TASK_CODECS.get(kind)
    if codec is None:
        raise ValueError(f"no message codec for task kind {kind!r}: the kinds are {sorted(TASK_CODECS)} "
                         "(add one to services.codec.convert.TASK_CODECS)")
    return codec


def task_to_message(task: CoreTask, stamp_ns: int = 0) -> Task:
    return _codec(task.kind).to_message(task, Header(stamp_ns=stamp_ns))


def task_from_message(msg: Task) -> CoreTask:
    """The core's task of a message (the message model has checked that its kind's fields are there)."""
    return _codec(msg.kind).from_message(msg)


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Yaw (rotation about z) of a unit quaternion, REP-103."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def costmap_from_message(msg: OccupancyGrid) -> Costmap:
    """The core's grid from an OccupancyGrid message (its size already checked by the message)."""
    values = np.asarray(msg.data, dtype=np.int16).reshape(msg.height, msg.width)
    return Costmap(values, msg.resolution, (msg.origin_x, msg.origin_y, msg.origin_yaw), float(msg.lethal))


def costmap_to_message(grid: Costmap, frame_id: str, stamp_ns: int = 0) -> OccupancyGrid:
    """An OccupancyGrid message of a grid of integer values (a map file's or a decoded one's)."""
    h, w = grid.shape
    ox, oy, yaw = grid.origin
    return OccupancyGrid(header=Header(stamp_ns=stamp_ns, frame_id=frame_id), resolution=grid.resolution, width=w,
                         height=h, origin_x=ox, origin_y=oy, origin_yaw=yaw, lethal=int(grid.lethal),
                         data=np.asarray(grid.values, dtype=np.int64).reshape(-1).tolist())
