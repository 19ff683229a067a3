"""Scenarios: the paper's tracks and obstacle scene, random scenes, and scenes/lanes from YAML files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from gpmppi.costmap import CostmapError, load_map_yaml
from gpmppi.tasks import GoalTask, LaneTask, Task
from gpmppi.yaml_file import yaml_error


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


# --- random scenes ---------------------------------------------------------------------------------------------


def random_obstacle_scene(
    seed: int,
    max_obstacles: int = 5,
    start: np.ndarray | None = None,
    goal: np.ndarray | None = None,
    tolerance: float = 0.5,
    radius_range: tuple[float, float] = (0.3, 1.0),
    margin: float = 0.5,
    max_attempts: int = 1000,
) -> Scenario:
    """Up to `max_obstacles` circles of random radius and centre between start and goal (seeded).

    Centres are drawn in the start-goal bounding box grown by 1 m; a circle is kept only if it stays
    `margin` [m] clear of the start and `margin` clear of the goal's tolerance disc, so a scene never
    covers its start or goal. Circles may overlap each other (a wall is a fair test).
    """
    rng = np.random.default_rng(seed)
    s = np.array([0.0, 0.0, np.pi / 4, 0.0, 0.0]) if start is None else np.asarray(start, dtype=np.float64)
    g = np.array([7.0, 5.0]) if goal is None else np.asarray(goal, dtype=np.float64)
    lo = np.minimum(s[:2], g) - 1.0
    hi = np.maximum(s[:2], g) + 1.0
    count = int(rng.integers(1, max_obstacles + 1))
    circles: list[list[float]] = []
    for _ in range(max_attempts):
        if len(circles) == count:
            break
        c = rng.uniform(lo, hi)
        r = float(rng.uniform(*radius_range))
        if np.linalg.norm(c - s[:2]) < r + margin or np.linalg.norm(c - g) < r + tolerance + margin:
            continue
        circles.append([float(c[0]), float(c[1]), r])
    obstacles = np.array(circles, dtype=np.float64).reshape(-1, 3)
    task = GoalTask(goal=g, tolerance=tolerance, obstacles=obstacles)
    return Scenario(f"random_{seed}", task, s.copy())


def infeasibility(scenario: Scenario, robot_radius: float = 0.0) -> list[str]:
    """Why a scenario cannot be done (empty if it can): its task's kind says (`start_problems`: start or goal inside an
    obstacle, start off the lane)."""
    return scenario.task.start_problems(scenario.start, robot_radius)


# --- scene and lane files ----------------------------------------------------------------------------------------

_DATA = Path(__file__).resolve().parent / "data"


class ScenarioFileError(ValueError):
    """A scene or lane file that cannot be used; the message names the file and the field."""


class _ObstacleModel(BaseModel):
    model_config = ConfigDict(extra="forbid")
    x: float = Field(description="centre x [m]", allow_inf_nan=False)
    y: float = Field(description="centre y [m]", allow_inf_nan=False)
    r: float = Field(gt=0, description="radius [m]", allow_inf_nan=False)


class _PoseModel(BaseModel):
    model_config = ConfigDict(extra="forbid")
    x: float = Field(allow_inf_nan=False, description="position x [m]")
    y: float = Field(allow_inf_nan=False, description="position y [m]")
    yaw: float = Field(0.0, allow_inf_nan=False, description="heading [rad], counter-clockwise from +x")


class SceneFile(BaseModel):
    """An obstacle scene: start pose, goal with tolerance, circles."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field("scene", description="scene name used in reports")
    start: _PoseModel = Field(description="start pose; the robot starts at rest")
    goal: tuple[float, float] = Field(description="goal position [x, y] in m")
    tolerance: float = Field(0.5, gt=0, allow_inf_nan=False, description="goal radius [m]")
    obstacles: list[_ObstacleModel] = Field(default_factory=list, description="circles {x, y, r}")
    map: str | None = Field(None, description="obstacles as an occupancy grid: a map_server map YAML (image, "
                            "resolution, origin, occupied_thresh, free_thresh, negate; a PGM image), relative to this "
                            "file")


class LaneFile(BaseModel):
    """A lane: a centre polyline of at least two points and a half-width."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field("lane", description="lane name used in reports")
    centerline: list[tuple[float, float]] = Field(min_length=2, description="centre polyline [[x, y], ...] in m")
    half_width: float = Field(gt=0, allow_inf_nan=False, description="half lane width [m]")
    speed_target: float = Field(1.75, ge=0, allow_inf_nan=False, description="speed target [m/s]")
    closed: bool = Field(True, description="whether the last point joins the first")
    start: _PoseModel | None = Field(None, description="start pose; default: first point, along the first segment")


def _read_yaml(path: Path, kind: str) -> object:
    if not path.is_file():
        raise ScenarioFileError(f"{kind} file {path}: not found")
    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ScenarioFileError(f"{kind} file {yaml_error(path, e)}") from e


def _validated(model: type[BaseModel], data: object, path: Path, kind: str) -> BaseModel:
    try:
        return model.model_validate(data)
    except ValidationError as e:
        first = e.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "(top level)"
        raise ScenarioFileError(
            f"{kind} file {path}: field '{where}': {first['msg']} (see the shipped {kind}_*.yaml examples)"
        ) from e


def load_scene(path: str | Path) -> Scenario:
    """Read an obstacle scene from YAML (see gpmppi/data/scene_*.yaml)."""
    p = Path(path)
    f = _validated(SceneFile, _read_yaml(p, "scene"), p, "scene")
    assert isinstance(f, SceneFile)
    obstacles = np.array([[o.x, o.y, o.r] for o in f.obstacles], dtype=np.float64).reshape(-1, 3)
    costmap = None
    if f.map is not None:
        try:
            costmap = load_map_yaml(p.parent / f.map)
        except CostmapError as e:
            raise ScenarioFileError(f"scene file {p}: field 'map': {e}") from e
    try:
        task = GoalTask(goal=np.array(f.goal), tolerance=f.tolerance, obstacles=obstacles, costmap=costmap)
    except ValueError as e:
        raise ScenarioFileError(f"scene file {p}: {e}") from e
    return Scenario(f.name, task, np.array([f.start.x, f.start.y, f.start.yaw, 0.0, 0.0]))


def load_lane(path: str | Path) -> Scenario:
    """Read a lane from YAML (see gpmppi/data/lane_*.yaml)."""
    p = Path(path)
    f = _validated(LaneFile, _read_yaml(p, "lane"), p, "lane")
    assert isinstance(f, LaneFile)
    centre = np.array(f.centerline, dtype=np.float64)
    try:
        task = LaneTask(centre, half_width=f.half_width, speed_target=f.speed_target, closed=f.closed)
    except ValueError as e:
        raise ScenarioFileError(f"lane file {p}: field 'centerline': {e}") from e
    if f.start is not None:
        start = np.array([f.start.x, f.start.y, f.start.yaw, 0.0, 0.0])
    else:
        d = centre[1] - centre[0]
        start = np.array([centre[0, 0], centre[0, 1], float(np.arctan2(d[1], d[0])), 0.0, 0.0])
    return Scenario(f.name, task, start)


def shipped_scene_files() -> list[Path]:
    """The example scenes shipped in gpmppi/data/."""
    return sorted(_DATA.glob("scene_*.yaml"))


def shipped_lane_files() -> list[Path]:
    """The example lanes shipped in gpmppi/data/."""
    return sorted(_DATA.glob("lane_*.yaml"))


def lane_scenario(name: str) -> Scenario:
    """A named lane: 'circle', 'square', or a path to a lane YAML file."""
    if name == "circle":
        return circle_lane()
    if name == "square":
        return square_lane()
    return load_lane(name)
