"""Cost terms and the lane distance lookup (against brute force over all segments)."""

from __future__ import annotations

import numpy as np
import pytest

from gpmppi.costmap import NO_GRID
from gpmppi.mppi.bundles import N_COST_TERMS, TaskArgs
from gpmppi.mppi.critics import collision, deviation, goal, lane_exit, slip, speed, terminal, variance
from gpmppi.mppi.critics.base import Step
from gpmppi.mppi.lane import LaneLookup, brute_force_distance, build_lane_lookup, lane_distance, polyline_segments
from gpmppi.scenarios import circle_lane, square_lane


def _dist(lane: LaneLookup, x: float, y: float) -> float:
    return lane_distance(lane.segments, lane.cell_start, lane.candidates, lane.origin, lane.inv_cell, lane.width,
                         lane.height, x, y)


def _check_lookup(points: np.ndarray, closed: bool, box: tuple[float, float, float, float], seed: int) -> None:
    lane = build_lane_lookup(points, closed, margin=3.0, cell=0.1)
    rng = np.random.default_rng(seed)
    # points inside and outside the lookup grid (outside falls back to brute force)
    xs = rng.uniform(box[0] - 4, box[1] + 4, 4000)
    ys = rng.uniform(box[2] - 4, box[3] + 4, 4000)
    got = np.array([_dist(lane, x, y)
                    for x, y in zip(xs, ys, strict=True)])
    ref = np.array([brute_force_distance(lane.segments, x, y) for x, y in zip(xs, ys, strict=True)])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)


def test_circle_lane_distance_matches_brute_force() -> None:
    sc = circle_lane()
    _check_lookup(sc.task.centerline, True, (-11, 11, -11, 11), 0)
    # and it is the distance to the circle itself up to the chord sagitta
    lane = build_lane_lookup(sc.task.centerline, True, margin=3.0)
    d = _dist(lane, 9.0, 0.0)
    assert d == pytest.approx(0.75, abs=2e-3)


def test_square_and_open_polyline_distance_match_brute_force() -> None:
    _check_lookup(square_lane().task.centerline, True, (-4, 24, -4, 24), 1)
    zigzag = np.array([[0.0, 0.0], [3.0, 2.0], [6.0, -1.0], [9.0, 3.0], [12.0, 0.0]])
    _check_lookup(zigzag, False, (-3, 15, -4, 6), 2)


def test_a_long_winding_path_matches_brute_force() -> None:
    # many segments, each cell searching only its block's list (a Nav2-like path: 0.25 m steps that wander)
    rng = np.random.default_rng(5)
    heading = np.cumsum(rng.normal(0.0, 0.3, 240))
    pts = np.cumsum(0.25 * np.column_stack([np.cos(heading), np.sin(heading)]), axis=0)
    lo, hi = pts.min(0), pts.max(0)
    _check_lookup(pts, False, (lo[0], hi[0], lo[1], hi[1]), 3)


def test_open_polyline_has_no_closing_segment() -> None:
    pts = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    assert polyline_segments(pts, closed=False).shape[0] == 2
    assert polyline_segments(pts, closed=True).shape[0] == 3
    lane = build_lane_lookup(pts, False, margin=2.0)
    # (2, 8) is 2 m from the closing chord (0,0)-(10,10) of a closed lane but 8 m from the open one
    d = _dist(lane, 2.0, 8.0)
    assert d == pytest.approx(8.0)


def test_degenerate_polyline_is_rejected() -> None:
    with pytest.raises(ValueError, match="centerline"):
        polyline_segments(np.zeros((4, 2)), closed=True)


def _at(x: float = 0.0, y: float = 0.0, v: float = 0.0, w: float = 0.0, u: tuple = (0.0, 0.0),
        var: tuple = (0.0, 0.0), hw: float = 1.0, radii: np.ndarray | None = None, d: float = 0.0) -> Step:
    """A step as the critics' terms read it (`critics.base.Step`), lane direction +x."""
    return Step(x, y, 0.0, v, w, u[0], u[1], var[0], var[1], hw, np.zeros(0) if radii is None else radii, (), d, 1.0,
                0.0)


def _geo(half_width: float = 1.0, speed_target: float = 0.0, obstacles: np.ndarray | None = None) -> tuple:
    """The task as the critics' terms read it (`TaskArgs`, by name)."""
    return TaskArgs(kind=0, seg=np.zeros((1, 5)), cell_start=np.zeros(2, dtype=np.int64),
                    candidates=np.zeros(0, dtype=np.int32), field=np.zeros((1, 1, 3)), origin=np.zeros(2), inv_cell=1.0,
                    half_width=half_width, tightened_hw=np.ones(1), speed_target=speed_target, goal=np.zeros(2),
                    obstacles=np.zeros((0, 3)) if obstacles is None else obstacles, radii=np.zeros((1, 0)),
                    grid=NO_GRID[0], grid_frame=NO_GRID[1])


def test_cost_terms() -> None:
    w = np.zeros(N_COST_TERMS)  # straight-line goal distance; no parameter read except speed's along_lane (off)
    g = _geo()
    assert variance.variance_cost(10.0, w, 0, g, _at(var=(0.01, 0.02))) == pytest.approx(0.3)
    assert deviation.deviation_cost(4.0, w, 0, _geo(half_width=2.0), _at(d=0.5)) == pytest.approx(0.25)
    assert slip.slip_cost(2.0, w, 0, g, _at(v=1.0, w=0.5, u=(1.5, 0.0))) == pytest.approx(1.0)
    assert lane_exit.lane_exit_cost(100.0, w, 0, g, _at(d=1.0, hw=0.9), 0.9**3) == pytest.approx(72.9)
    assert lane_exit.lane_exit_cost(100.0, w, 0, g, _at(d=0.8, hw=0.9), 1.0) == 0.0
    assert speed.speed_cost(1.0, w, 0, _geo(speed_target=1.75), _at(v=1.0)) == pytest.approx(0.5625)
    obstacles = np.array([[0.0, 0.0, 1.0], [5.0, 0.0, 0.5]])
    # the indicator compares distances with radii (not squared distance with a length)
    og = _geo(obstacles=obstacles)
    assert collision.collision_cost(7.0, w, 0, og, _at(0.0, 1.2, radii=np.array([1.3, 0.5]))) == 7.0
    assert collision.collision_cost(7.0, w, 0, og, _at(0.0, 1.2, radii=np.array([1.1, 0.5]))) == 0.0
    assert collision.collision_cost(7.0, w, 0, og, _at(5.3, 0.0, radii=np.array([1.1, 0.5]))) == 7.0
    assert goal.goal_cost(2.0, w, 0, g, _at(3.0, 4.0)) == pytest.approx(10.0)
    assert terminal.terminal_cost(2.0, w, 0, g, _at(3.0, 4.0)) == pytest.approx(10.0)
