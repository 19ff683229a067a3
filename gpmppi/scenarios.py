"""Scenarios: the paper's tracks and obstacle scene, each with a start state."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpmppi.tasks import GoalTask, LaneTask, Task


@dataclass(frozen=True)
class Scenario:
    name: str
    task: Task
    start: np.ndarray  # [X, Y, theta, v, omega]


def circle_lane(radius: float = 8.25, half_width: float = 1.75, speed: float = 1.75, points: int = 360) -> Scenario:
    """Counter-clockwise circle centred at the origin; start on it at (radius, 0) heading +y."""
    a = np.linspace(0.0, 2.0 * np.pi, points, endpoint=False)
    centre = np.stack([radius * np.cos(a), radius * np.sin(a)], axis=1)
    task = LaneTask(centre, half_width=half_width, speed_target=speed, closed=True)
    return Scenario("circle", task, np.array([radius, 0.0, np.pi / 2, 0.0, 0.0]))


def square_lane(side: float = 20.0, half_width: float = 2.75, speed: float = 1.75, per_side: int = 40) -> Scenario:
    """Counter-clockwise square with corners (0,0)-(side,side); start at (side/2, 0) heading +x."""
    t = np.linspace(0.0, side, per_side, endpoint=False)
    z = np.zeros_like(t)
    s = np.full_like(t, side)
    centre = np.concatenate(
        [np.stack([t, z], 1), np.stack([s, t], 1), np.stack([side - t, s], 1), np.stack([z, side - t], 1)]
    )
    task = LaneTask(centre, half_width=half_width, speed_target=speed, closed=True)
    return Scenario("square", task, np.array([side / 2, 0.0, 0.0, 0.0, 0.0]))


PAPER_OBSTACLES = np.array(
    [[2.0, 1.0, 0.7], [1.0, 4.0, 0.9], [5.0, 5.0, 0.75], [6.0, 1.0, 0.85], [6.0, 4.0, 0.85]]
)


def paper_obstacle_scene() -> Scenario:
    """The paper's scene: start (0, 0, pi/4), goal (7, 5) within 0.5 m, five circles."""
    task = GoalTask(goal=np.array([7.0, 5.0]), tolerance=0.5, obstacles=PAPER_OBSTACLES.copy())
    return Scenario("paper_obstacles", task, np.array([0.0, 0.0, np.pi / 4, 0.0, 0.0]))
