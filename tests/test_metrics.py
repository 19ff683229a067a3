"""Metrics on hand-made trajectories whose scores are known in closed form."""

from __future__ import annotations

import numpy as np
import pytest

from gpmppi.evaluation.metrics import (
    first_goal_index,
    goal_outcome,
    lane_exit_count,
    lane_rmse_mm,
    mean_std,
    obstacle_clearance,
    path_length,
)
from gpmppi.scenarios import circle_lane, square_lane
from gpmppi.tasks import distance_to_polyline

SQUARE = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])


def test_distance_is_to_segments_not_vertices() -> None:
    pts = np.array([[5.0, 0.3], [5.0, -0.2], [10.5, 5.0], [-1.0, -1.0], [5.0, 5.0]])
    d = distance_to_polyline(pts, SQUARE, closed=True)
    np.testing.assert_allclose(d, [0.3, 0.2, 0.5, np.sqrt(2.0), 5.0], atol=1e-12)


def test_open_polyline_does_not_close() -> None:
    # (0, 5) is on the closing edge of the square, and 5 m from the open polyline (nearest: (0, 0) and (0, 10))
    d_open = distance_to_polyline(np.array([[0.0, 5.0]]), SQUARE, closed=False)
    d_closed = distance_to_polyline(np.array([[0.0, 5.0]]), SQUARE, closed=True)
    assert d_closed[0] == pytest.approx(0.0)
    assert d_open[0] == pytest.approx(5.0)


def test_rmse_of_constant_offset_on_square_edge() -> None:
    x = np.linspace(1.0, 9.0, 50)
    pts = np.stack([x, np.full_like(x, 0.03)], 1)
    assert lane_rmse_mm(pts, SQUARE) == pytest.approx(30.0)


def test_rmse_of_alternating_offsets() -> None:
    # offsets 10 mm and 40 mm alternately: rmse = sqrt((100 + 1600) / 2) mm
    x = np.linspace(1.0, 9.0, 40)
    y = np.where(np.arange(40) % 2 == 0, 0.01, -0.04)
    assert lane_rmse_mm(np.stack([x, y], 1), SQUARE) == pytest.approx(np.sqrt(850.0))


def test_rmse_on_paper_circle_matches_radial_error() -> None:
    lane = circle_lane().task
    a = np.linspace(0.0, 2 * np.pi, 1000)
    r = 8.25 + 0.025
    pts = np.stack([r * np.cos(a), r * np.sin(a)], 1)
    # the 360-gon's chords sit inside the circle by at most R(1 - cos(pi/360)) = 0.31 mm (mean 2/3 of it)
    chord_bias_mm = 2 / 3 * 8250 * (1 - np.cos(np.pi / 360))
    assert lane_rmse_mm(pts, lane.centerline) == pytest.approx(25.0 + chord_bias_mm, abs=0.02)


def test_lane_exits_counts_transitions() -> None:
    y = np.array([0.0, 1.0, 3.0, 3.5, 1.0, 0.0, -3.0, 0.0, 3.0])
    pts = np.stack([np.full_like(y, 5.0), y], 1)
    lane = square_lane(side=10.0, half_width=2.75).task
    assert lane_exit_count(pts, lane.centerline, lane.half_width) == 3
    assert lane_exit_count(pts[:2], lane.centerline, lane.half_width) == 0


def test_clearance_and_path_length() -> None:
    obstacles = np.array([[3.0, 0.0, 1.0], [0.0, 5.0, 0.5]])
    pts = np.array([[0.0, 0.0], [1.5, 0.0], [2.5, 0.0]])
    np.testing.assert_allclose(obstacle_clearance(pts, obstacles), [2.0, 0.5, -0.5])
    np.testing.assert_allclose(obstacle_clearance(pts, obstacles, robot_radius=0.2), [1.8, 0.3, -0.7])
    assert np.all(np.isinf(obstacle_clearance(pts, np.zeros((0, 3)))))
    assert path_length(np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 5.0]])) == pytest.approx(6.0)


def _line(times: np.ndarray, speed: float) -> np.ndarray:
    return np.stack([speed * times, np.zeros_like(times)], 1)


def test_goal_outcome_success_and_time() -> None:
    t = np.arange(0.0, 10.0, 0.1)
    pts = _line(t, 1.0)  # reaches x = 4.5 (goal 5 within 0.5) at t = 4.5 s
    out = goal_outcome(t, pts, np.array([5.0, 0.0]), 0.5, np.array([[2.0, 2.0, 1.0]]), time_limit=20.0)
    assert out.success and not out.collided
    assert out.time_to_goal_s == pytest.approx(4.5)
    assert out.min_clearance_m == pytest.approx(1.0)
    assert first_goal_index(pts, np.array([5.0, 0.0]), 0.5) == 45


def test_goal_outcome_collision_before_goal_fails() -> None:
    t = np.arange(0.0, 10.0, 0.1)
    out = goal_outcome(t, _line(t, 1.0), np.array([5.0, 0.0]), 0.5, np.array([[2.0, 0.3, 0.5]]), time_limit=20.0)
    assert not out.success and out.collided
    assert out.time_to_goal_s == pytest.approx(4.5)


def test_goal_outcome_collision_after_goal_is_ignored_and_late_goal_fails() -> None:
    t = np.arange(0.0, 10.0, 0.1)
    obstacles = np.array([[8.0, 0.0, 0.5]])  # hit at x = 7.5, after the goal
    out = goal_outcome(t, _line(t, 1.0), np.array([5.0, 0.0]), 0.5, obstacles, time_limit=20.0)
    assert out.success and not out.collided
    late = goal_outcome(t, _line(t, 1.0), np.array([5.0, 0.0]), 0.5, np.zeros((0, 3)), time_limit=4.0)
    assert not late.success and np.isnan(late.time_to_goal_s)


def test_mean_std_ignores_nan() -> None:
    m, s = mean_std([1.0, 3.0, float("nan")])
    assert (m, s) == (2.0, 1.0)
    assert all(np.isnan(mean_std([])))
