"""What the planner is asked to do, as plain arrays: follow a lane, or reach a goal.

A task type is the plain part of its task kind: what needs no planner, as methods every kind's task has, so nothing
outside the kinds asks which kind a task is:

* `kind`: the kind's name (a task message's `kind`; the message codecs are keyed by it, `services/codec/convert.py`);
* `outline()`: what a view draws of it (`TaskOutline`: a lane, circles, a goal, one line of text);
* `start_problems(start, robot_radius)`: why a run cannot start at `start` (a scenario's feasibility);
* `cautious(speed_scale, approach)`: the task while the ground is unknown (`gpmppi.mppi.caution`);
* `with_costmap(costmap, replace_own)`: the task in a world with this occupancy grid (`PlannerCycle.on_costmap`).

The planner's part of a kind is its `gpmppi.mppi.task_kinds.TaskKind`, the evaluation's its
`gpmppi.evaluation.task_runs.TaskRun`; all three are keyed by the task type.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar, Literal

import numpy as np

from gpmppi.costmap import Costmap


@dataclass(frozen=True)
class TaskOutline:
    """What a view draws of a task, as plain geometry [m]; the parts a kind has not are None or empty."""

    summary: str  # one line for the event log, e.g. "lane, 360 points, half-width 1.75 m, speed 1.75 m/s"
    lane: np.ndarray | None = None  # (P, 2) centre polyline
    closed: bool = False  # the lane is a loop
    half_width: float = 0.0  # the lane's half-width
    circles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (K, 3) obstacles [x, y, r]
    goal: np.ndarray | None = None  # (2,) goal point
    tolerance: float = 0.0  # the goal is reached within this distance
    # what a plan's per-step bound (`Plan.tightened`) is: the lane's tightened half-width, or the circles' inflation
    bounds: Literal["half_width", "inflation"] = "inflation"


@dataclass(frozen=True)
class LaneTask:
    """Follow a lane: a centre polyline (P, 2) [m] with a constant half-width [m]."""

    centerline: np.ndarray
    half_width: float
    speed_target: float = 1.75
    closed: bool = True

    kind: ClassVar[str] = "lane"

    def __post_init__(self) -> None:
        c = np.asarray(self.centerline, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != 2 or c.shape[0] < 2:
            raise ValueError(f"lane centerline must be (P>=2, 2) points, got shape {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError("lane centerline has non-finite points")
        if not (np.isfinite(self.half_width) and self.half_width > 0):
            raise ValueError(f"lane half_width must be a positive number, got {self.half_width}")
        if not (np.isfinite(self.speed_target) and self.speed_target >= 0):
            raise ValueError(f"lane speed_target must be >= 0, got {self.speed_target}")
        object.__setattr__(self, "centerline", np.ascontiguousarray(c))

    def outline(self) -> TaskOutline:
        summary = (f"lane, {len(self.centerline)} points, half-width {self.half_width:.2f} m, speed "
                   f"{self.speed_target:.2f} m/s")
        return TaskOutline(summary, lane=self.centerline, closed=self.closed, half_width=float(self.half_width),
                           bounds="half_width")

    def start_problems(self, start: np.ndarray, robot_radius: float) -> list[str]:
        """Why a run cannot start at `start` [X, Y, ...]: off the lane."""
        d = float(distance_to_polyline(np.asarray(start)[None, :2], self.centerline, self.closed)[0])
        if d > self.half_width:
            return [f"start is {d:.2f} m from the lane centre, outside the half-width {self.half_width:g} m"]
        return []

    def cautious(self, speed_scale: float, approach: tuple[float, float] | None = None) -> LaneTask:
        """The lane at the scaled speed target (`approach` is a goal's)."""
        return dataclasses.replace(self, speed_target=self.speed_target * speed_scale)

    def with_costmap(self, costmap: Costmap | None, replace_own: bool = False) -> LaneTask:
        """A lane plans no obstacles: itself."""
        return self


@dataclass(frozen=True)
class GoalTask:
    """Reach `goal` (2,) within `tolerance` [m] avoiding circles `obstacles` (K, 3) = [x, y, r] and the lethal cells
    of `costmap` (an occupancy grid, or None). With `approach_speed` [m/s] set, the commanded speed is bounded by
    the speed from which braking at `approach_decel` [m/s^2] comes down to `approach_speed` at the goal's tolerance
    (`speed_bound`; the caution on unknown ground sets them: `cautious`)."""

    goal: np.ndarray
    tolerance: float = 0.5
    obstacles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    costmap: Costmap | None = None
    approach_speed: float | None = None
    approach_decel: float = 0.0

    kind: ClassVar[str] = "goal"

    def __post_init__(self) -> None:
        g = np.asarray(self.goal, dtype=np.float64).reshape(-1)
        o = np.asarray(self.obstacles, dtype=np.float64).reshape(-1, 3)
        if g.shape != (2,) or not np.all(np.isfinite(g)):
            raise ValueError(f"goal must be 2 finite numbers, got {self.goal!r}")
        if not np.all(np.isfinite(o)) or np.any(o[:, 2] <= 0):
            raise ValueError("obstacles must be finite [x, y, r] rows with r > 0")
        if not (np.isfinite(self.tolerance) and self.tolerance > 0):
            raise ValueError(f"goal tolerance must be > 0, got {self.tolerance}")
        if self.approach_speed is not None and not (np.isfinite(self.approach_speed) and self.approach_speed > 0):
            raise ValueError(f"goal approach_speed must be a positive number of m/s or None, got {self.approach_speed}")
        if not (np.isfinite(self.approach_decel) and self.approach_decel >= 0):
            raise ValueError(f"goal approach_decel must be >= 0 m/s^2, got {self.approach_decel}")
        if self.costmap is not None and not isinstance(self.costmap, Costmap):
            raise ValueError(f"costmap must be a gpmppi.costmap.Costmap or None, got {type(self.costmap).__name__}")
        object.__setattr__(self, "goal", g)
        object.__setattr__(self, "obstacles", np.ascontiguousarray(o))

    def outline(self) -> TaskOutline:
        return TaskOutline(f"goal {self.goal.tolist()}, {self.obstacles.shape[0]} obstacles", circles=self.obstacles,
                           goal=self.goal, tolerance=float(self.tolerance), bounds="inflation")

    def start_problems(self, start: np.ndarray, robot_radius: float) -> list[str]:
        """Why a run cannot start at `start` [X, Y, ...]: start or goal inside a circle or the grid's obstacles."""
        problems: list[str] = []
        sx, sy = float(start[0]), float(start[1])
        for i, (x, y, r) in enumerate(self.obstacles):
            if np.hypot(sx - x, sy - y) <= r + robot_radius:
                problems.append(f"start ({sx:g}, {sy:g}) is inside obstacle {i}")
            if np.hypot(self.goal[0] - x, self.goal[1] - y) + self.tolerance <= r + robot_radius:
                problems.append(f"goal ({self.goal[0]:g}, {self.goal[1]:g}) lies wholly inside obstacle {i}")
        if self.costmap is not None:
            clear = self.costmap.clearance(np.stack([np.array([sx, sy]), self.goal]), robot_radius)
            if clear[0] < 0.0:
                problems.append(f"start ({sx:g}, {sy:g}) is in the map's obstacles")
            if clear[1] + self.tolerance < 0.0:
                problems.append(f"goal ({self.goal[0]:g}, {self.goal[1]:g}) lies wholly in the map's obstacles")
        return problems

    def cautious(self, speed_scale: float, approach: tuple[float, float] | None = None) -> GoalTask:
        """The goal approached at most at `approach` = (speed [m/s] at the tolerance, braking [m/s^2] before it)
        (None: unchanged), so that the robot can still turn into the goal on ground whose grip no trained ground
        tells (docs/new_ground.md)."""
        if approach is None:
            return self
        return dataclasses.replace(self, approach_speed=float(approach[0]), approach_decel=float(approach[1]))

    def speed_bound(self, position: np.ndarray) -> float | None:
        """The commanded speed's bound [m/s] at `position` (2,): `sqrt(approach_speed^2 + 2 approach_decel
        (d - tolerance))` at distance d from the goal (`approach_speed` within the tolerance); None without one."""
        if self.approach_speed is None:
            return None
        d = float(np.hypot(position[0] - self.goal[0], position[1] - self.goal[1]))
        return float(np.sqrt(self.approach_speed ** 2 + 2.0 * self.approach_decel * max(d - self.tolerance, 0.0)))

    def with_costmap(self, costmap: Costmap | None, replace_own: bool = False) -> GoalTask:
        """The goal among `costmap`'s obstacles (None: none but its circles). A task that brought its own grid keeps it,
        and without a grid it stays as it is, unless `replace_own` (a new grid replaces the world's)."""
        if not replace_own and (self.costmap is not None or costmap is None):
            return self
        return dataclasses.replace(self, costmap=costmap)


Task = LaneTask | GoalTask


def polyline_segments(centerline: np.ndarray, closed: bool) -> tuple[np.ndarray, np.ndarray]:
    """Segment start points (S, 2) and direction vectors (S, 2) of a polyline (closing it if `closed`)."""
    c = np.asarray(centerline, dtype=np.float64)
    ends = np.roll(c, -1, axis=0) if closed else c[1:]
    starts = c if closed else c[:-1]
    return starts, ends - starts


def distance_to_polyline(points: np.ndarray, centerline: np.ndarray, closed: bool = True) -> np.ndarray:
    """Euclidean distance (T,) from each point (T, 2) to the closest point of the polyline (segments, not vertices)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    starts, dirs = polyline_segments(centerline, closed)
    len2 = np.einsum("sd,sd->s", dirs, dirs)
    len2 = np.where(len2 > 0.0, len2, 1.0)  # a repeated vertex is a zero-length segment: its start is its point
    out = np.empty(p.shape[0])
    chunk = 2048  # bounds the (chunk, S, 2) temporary for long runs over finely sampled lanes
    for i in range(0, p.shape[0], chunk):
        rel = p[i : i + chunk, None, :] - starts[None, :, :]
        t = np.clip(np.einsum("tsd,sd->ts", rel, dirs) / len2, 0.0, 1.0)
        diff = rel - t[..., None] * dirs[None, :, :]
        out[i : i + chunk] = np.sqrt(np.min(np.einsum("tsd,tsd->ts", diff, diff), axis=1))
    return out


def polyline_length(centerline: np.ndarray, closed: bool = True) -> float:
    """Length [m] of a polyline (with its closing segment if `closed`)."""
    _, dirs = polyline_segments(centerline, closed)
    return float(np.sum(np.linalg.norm(dirs, axis=1)))


def progress_along_polyline(points: np.ndarray, centerline: np.ndarray, closed: bool = True) -> np.ndarray:
    """Arc length (T,) [m] from the polyline's first point to the point of it closest to each point (T, 2).

    Ties between equally close segments go to the earliest segment, so a point where an open lane's end meets its
    start counts as the start.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    starts, dirs = polyline_segments(centerline, closed)
    seg_len = np.linalg.norm(dirs, axis=1)
    offset = np.concatenate([[0.0], np.cumsum(seg_len)[:-1]])
    len2 = np.where(seg_len > 0.0, seg_len * seg_len, 1.0)
    out = np.empty(p.shape[0])
    chunk = 2048
    for i in range(0, p.shape[0], chunk):
        rel = p[i : i + chunk, None, :] - starts[None, :, :]
        t = np.clip(np.einsum("tsd,sd->ts", rel, dirs) / len2, 0.0, 1.0)
        diff = rel - t[..., None] * dirs[None, :, :]
        best = np.argmin(np.einsum("tsd,tsd->ts", diff, diff), axis=1)
        rows = np.arange(best.size)
        out[i : i + chunk] = offset[best] + t[rows, best] * seg_len[best]
    return out
