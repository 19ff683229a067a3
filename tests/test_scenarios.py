"""Scenarios: random scenes never cover start or goal; scene/lane files load or fail naming file and field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gpmppi.scenarios import (
    ScenarioFileError,
    circle_lane,
    infeasibility,
    load_lane,
    load_scene,
    paper_obstacle_scene,
    random_obstacle_scene,
    shipped_lane_files,
    shipped_scene_files,
    square_lane,
)
from gpmppi.tasks import GoalTask, LaneTask, distance_to_polyline


def test_paper_geometry() -> None:
    c, s = circle_lane().task, square_lane().task
    assert isinstance(c, LaneTask) and isinstance(s, LaneTask)
    assert (c.half_width, s.half_width, c.speed_target) == (1.75, 2.75, 1.75)
    np.testing.assert_allclose(np.linalg.norm(c.centerline, axis=1), 8.25)
    assert np.ptp(s.centerline[:, 0]) == pytest.approx(20.0)
    for sc in (circle_lane(), square_lane()):
        assert distance_to_polyline(sc.start[None, :2], sc.task.centerline)[0] < 1e-9


def test_random_scene_never_covers_start_or_goal() -> None:
    counts = set()
    for seed in range(2000):
        sc = random_obstacle_scene(seed)
        task = sc.task
        assert isinstance(task, GoalTask)
        counts.add(task.obstacles.shape[0])
        d_start = np.linalg.norm(task.obstacles[:, :2] - sc.start[None, :2], axis=1) - task.obstacles[:, 2]
        d_goal = np.linalg.norm(task.obstacles[:, :2] - task.goal[None], axis=1) - task.obstacles[:, 2]
        assert np.all(d_start >= 0.5 - 1e-12), seed
        assert np.all(d_goal >= task.tolerance + 0.5 - 1e-12), seed
        assert infeasibility(sc) == [], seed
    assert counts == {1, 2, 3, 4, 5}


def test_random_scene_is_seeded() -> None:
    a, b, c = random_obstacle_scene(3), random_obstacle_scene(3), random_obstacle_scene(4)
    np.testing.assert_array_equal(a.task.obstacles, b.task.obstacles)
    assert a.task.obstacles.shape != c.task.obstacles.shape or not np.allclose(a.task.obstacles, c.task.obstacles)


def test_shipped_files_load() -> None:
    scenes, lanes = shipped_scene_files(), shipped_lane_files()
    assert scenes and lanes
    for f in scenes:
        assert infeasibility(load_scene(f)) == []
    for f in lanes:
        assert infeasibility(load_lane(f)) == []
    paper = load_scene(next(f for f in scenes if f.name == "scene_paper.yaml"))
    np.testing.assert_allclose(paper.task.obstacles, paper_obstacle_scene().task.obstacles)
    np.testing.assert_allclose(paper.start, paper_obstacle_scene().start, atol=1e-9)


def test_infeasible_scene_is_reported(tmp_path: Path) -> None:
    f = tmp_path / "bad.yaml"
    f.write_text("start: {x: 0, y: 0}\ngoal: [5, 0]\nobstacles: [{x: 5, y: 0, r: 1.0}, {x: 0.2, y: 0, r: 0.5}]\n")
    problems = infeasibility(load_scene(f))
    assert any("goal" in p and "obstacle 0" in p for p in problems)
    assert any("start" in p and "obstacle 1" in p for p in problems)


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("start: {x: 0, y: 0}\ngoal: [5, 0]\nobstacles:\n  - {x: 1, y: 1, r: -1}\n", "obstacles.0.r"),
        ("start: {x: 0, y: 0}\ngoal: [5]\n", "goal.1"),
        ("goal: [5, 0]\n", "start"),
        ("start: {x: 0, y: 0}\ngoal: [5, 0]\nobstacle: []\n", "obstacle"),
        ("start: {x: 0, y: .nan}\ngoal: [5, 0]\n", "start.y"),
    ],
)
def test_malformed_scene_names_file_and_field(tmp_path: Path, text: str, field: str) -> None:
    f = tmp_path / "my_scene.yaml"
    f.write_text(text)
    with pytest.raises(ScenarioFileError) as e:
        load_scene(f)
    assert str(f) in str(e.value) and f"'{field}'" in str(e.value)


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("centerline: [[0, 0], [1, 0]]\nhalf_width: 0\n", "half_width"),
        ("centerline: [[0, 0]]\nhalf_width: 1\n", "centerline"),
        ("centerline: [[0, 0], [1, 0, 2]]\nhalf_width: 1\n", "centerline.1"),
        ("half_width: 1\n", "centerline"),
    ],
)
def test_malformed_lane_names_file_and_field(tmp_path: Path, text: str, field: str) -> None:
    f = tmp_path / "my_lane.yaml"
    f.write_text(text)
    with pytest.raises(ScenarioFileError) as e:
        load_lane(f)
    assert str(f) in str(e.value) and f"'{field}'" in str(e.value)


def test_missing_and_non_yaml_files(tmp_path: Path) -> None:
    with pytest.raises(ScenarioFileError, match="not found"):
        load_scene(tmp_path / "nope.yaml")
    f = tmp_path / "broken.yaml"
    f.write_text("start: [\n")
    with pytest.raises(ScenarioFileError, match="broken.yaml:2:1: YAML syntax error") as e:
        load_lane(f)
    assert "<unicode string>" not in str(e.value) and "\n" not in str(e.value)


def test_open_lane_default_start_faces_along_first_segment(tmp_path: Path) -> None:
    f = tmp_path / "l.yaml"
    f.write_text("centerline: [[1, 1], [1, 5], [4, 5]]\nhalf_width: 1.0\nclosed: false\n")
    sc = load_lane(f)
    np.testing.assert_allclose(sc.start, [1.0, 1.0, np.pi / 2, 0.0, 0.0])
    assert sc.task.closed is False
