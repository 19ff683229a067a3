"""Metrics on hand-made trajectories whose scores are known in closed form."""

from __future__ import annotations

import numpy as np
import pytest

from gpmppi.evaluation.metrics import (
    command_rates,
    first_goal_index,
    goal_outcome,
    lane_end_reached,
    lane_exit_count,
    lane_rmse_mm,
    mean_p95,
    mean_std,
    obstacle_clearance,
    path_length,
    top_terrain_confusion,
    true_weight_mean,
    unknown_delay_s,
    unknown_share,
    weight_switches_per_min,
)
from gpmppi.scenarios import circle_lane, square_lane
from gpmppi.tasks import distance_to_polyline, polyline_length, progress_along_polyline

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


# --- the open lane's end --------------------------------------------------------------------------------------------

ELL = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])  # open, 20 m long, ends at (10, 10) heading +y


def test_progress_along_an_open_polyline() -> None:
    assert polyline_length(ELL, closed=False) == pytest.approx(20.0)
    assert polyline_length(ELL, closed=True) == pytest.approx(20.0 + np.sqrt(200.0))
    pts = np.array([[-1.0, 0.5], [4.0, 0.3], [10.4, 3.0], [10.3, 12.0], [11.0, -1.0]])
    # before the start clips to 0, past the end to the length; the corner's outside is the corner (10 m)
    np.testing.assert_allclose(progress_along_polyline(pts, ELL, closed=False), [0.0, 4.0, 13.0, 20.0, 10.0])


def test_lane_end_reached_within_tolerance_or_past_the_end_and_in_the_lane() -> None:
    pts = np.array([
        [10.0, 9.4],  # 0.6 m before the end along the lane: not yet
        [10.2, 9.6],  # 0.4 m before it, 0.2 m off the centre line: there
        [10.3, 10.5],  # past the end, 0.58 m from the end point (inside the half-width 1): there
        [10.5, 11.0],  # past the end, 1.12 m from it: beyond the lane
        [11.2, 9.8],  # beside the last segment, 1.2 m off the centre line: not in the lane
        [0.0, 0.2],  # at the start
    ])
    assert lane_end_reached(pts, ELL, half_width=1.0, tolerance_m=0.5).tolist() == [
        False, True, True, False, False, False]
    # tolerance 0: only past the end counts
    assert lane_end_reached(pts[:3], ELL, 1.0, 0.0).tolist() == [False, False, True]
    assert lane_end_reached(np.zeros((0, 2)), ELL, 1.0).shape == (0,)


# --- command smoothness --------------------------------------------------------------------------------------------


def test_command_rates_and_their_mean_and_p95() -> None:
    t = np.array([0.0, 0.1, 0.2, 0.3])
    u = np.array([[0.0, 0.0], [0.1, -0.2], [0.3, 0.2], [0.3, 0.1]])
    r = command_rates(t, u)
    np.testing.assert_allclose(r, [[1.0, 2.0], [2.0, 4.0], [0.0, 1.0]])
    # numpy's linear percentile of 3 values: rank 0.95 * 2 = 1.9, between the 2nd and 3rd smallest
    assert mean_p95(r[:, 0]) == pytest.approx((1.0, 1.0 + 0.9 * (2.0 - 1.0)))
    assert mean_p95(r[:, 1]) == pytest.approx((7.0 / 3.0, 2.0 + 0.9 * (4.0 - 2.0)))
    # a trajectory's T+1 times: the commands' are the first T; uneven steps divide by their own dt
    np.testing.assert_allclose(command_rates(np.array([0.0, 0.1, 0.3, 0.4]), u[:3])[:, 0], [1.0, 1.0])


def test_command_rates_of_fewer_than_two_commands_are_empty_and_score_nan() -> None:
    assert command_rates(np.array([0.0, 0.1]), np.array([[1.0, 0.5]])).shape == (0, 2)
    assert command_rates(np.array([0.0]), np.zeros((0, 2))).shape == (0, 2)
    assert all(np.isnan(mean_p95(np.zeros(0))))
    with pytest.raises(ValueError):
        command_rates(np.array([0.0, 0.0]), np.zeros((2, 2)))


# --- terrain weights -----------------------------------------------------------------------------------------------

NAMES = ["asphalt", "grass", "tile"]


def _weights(true_col: list[float], on: list[str]) -> np.ndarray:
    """Rows whose weight on the driven terrain is `true_col[k]`, the rest spread evenly over the others."""
    w = np.zeros((len(on), 3))
    for k, (x, name) in enumerate(zip(true_col, on, strict=True)):
        w[k] = (1.0 - x) / 2.0
        if name in NAMES:
            w[k, NAMES.index(name)] = x
    return w


def test_true_weight_mean_is_time_averaged_after_settling_on_known_terrain() -> None:
    times = np.arange(7.0)  # six 1 s cycles
    driven = ["grass", "grass", "grass", "grass", "sand", "tile"]
    w = _weights([0.1, 0.1, 0.2, 0.6, 0.5, 0.9], driven)
    # after 3 s: cycle 3 (grass 0.6), cycle 4 on sand (left out), cycle 5 (tile 0.9)
    assert true_weight_mean(times, w, driven, NAMES) == pytest.approx((0.6 + 0.9) / 2)
    # settling after 2.5 s takes half of cycle 2 (grass 0.2)
    assert true_weight_mean(times, w, driven, NAMES, settle_s=2.5) == pytest.approx((0.5 * 0.2 + 0.6 + 0.9) / 2.5)
    # uneven cycles weigh by their duration: 1 s of 0.6, 3 s of 0.9
    t2 = np.array([0.0, 3.0, 4.0, 7.0])
    assert true_weight_mean(t2, _weights([0.0, 0.6, 0.9], ["tile"] * 3), ["tile"] * 3, NAMES) == pytest.approx(
        (0.6 + 3 * 0.9) / 4)


def test_true_weight_mean_is_none_without_anything_to_average() -> None:
    short = np.arange(30) * 0.1  # 29 cycles, ending at 2.9 s: shorter than the 3 s settling
    assert true_weight_mean(short, np.full((29, 3), 1 / 3), ["grass"] * 29, NAMES) is None
    t = np.arange(61) * 0.1
    assert true_weight_mean(t, np.full((60, 3), 1 / 3), ["sand"] * 60, NAMES) is None  # untrained terrain only
    assert true_weight_mean(t, np.zeros((60, 0)), ["grass"] * 60, NAMES) is None  # no weights
    assert true_weight_mean(np.zeros(1), np.zeros((0, 3)), [], NAMES) is None  # no cycles
    with pytest.raises(ValueError):
        true_weight_mean(t[:-1], np.full((60, 3), 1 / 3), ["grass"] * 60, NAMES)


def test_weight_switches_per_minute_count_argmax_changes() -> None:
    times = np.arange(7) * 5.0  # six 5 s cycles: half a minute
    w = np.array([[0.6, 0.2, 0.2], [0.5, 0.4, 0.1], [0.3, 0.6, 0.1], [0.2, 0.7, 0.1], [0.8, 0.1, 0.1],
                  [0.1, 0.1, 0.8]])
    # top terrain 0, 0, 1, 1, 0, 2: three changes in 0.5 min (counted from t = 0)
    assert weight_switches_per_min(times, w, settle_s=0.0) == pytest.approx(6.0)
    # by default after the first 3 s: the same three changes (at 10, 20 and 25 s) in 27 s
    assert weight_switches_per_min(times, w) == pytest.approx(3 / 0.45)
    ties = np.tile([0.5, 0.5, 0.0], (6, 1))  # a tie goes to the first every time: no change
    assert weight_switches_per_min(times, ties) == 0.0
    assert weight_switches_per_min(times[:2], w[:1]) == 0.0
    assert weight_switches_per_min(np.zeros(1), np.zeros((0, 3))) is None
    assert weight_switches_per_min(times, np.zeros((6, 0))) is None
    assert weight_switches_per_min(times[:2] * 0.5, w[:1]) is None  # a 2.5 s run: nothing after 3 s


def test_weight_switches_leave_out_the_first_answer_from_uniform_weights() -> None:
    """A 6 s obstacle run whose estimate leaves the uniform start for the right terrain at 0.5 s and keeps it: no
    switch (from t = 0 this scored 10 per minute); a later change of mind at 4 s is one in 3 s."""
    times = np.arange(61) * 0.1
    k = np.arange(60)
    settled = np.where(k[:, None] < 5, 1 / 3, np.array([0.1, 0.8, 0.1])[None, :])
    assert weight_switches_per_min(times, settled) == 0.0
    assert weight_switches_per_min(times, settled, settle_s=0.0) == pytest.approx(10.0)
    changed = np.where(k[:, None] < 40, settled, np.array([0.7, 0.2, 0.1])[None, :])
    assert weight_switches_per_min(times, changed) == pytest.approx(1 / (3.0 / 60.0))
    with pytest.raises(ValueError, match="weight rows need"):
        weight_switches_per_min(times[:-1], settled)


def test_top_terrain_confusion_of_hand_made_runs() -> None:
    names = ["asphalt", "grass", "tile"]
    t = np.arange(0.0, 10.5, 0.5)  # 20 cycles of 0.5 s: 14 after the first 3 s
    on_asphalt = np.tile([0.2, 0.3, 0.5], (20, 1))  # tile leads until 5 s (4 cycles after 3 s), then asphalt
    on_asphalt[10:] = [0.9, 0.05, 0.05]
    on_grass = np.tile([0.1, 0.8, 0.1], (20, 1))
    rows, m = top_terrain_confusion(
        [("asphalt", t, on_asphalt), ("grass", t, on_grass), ("sand", t, on_grass), ("tile", t[:5], on_grass[:4])],
        names)
    assert rows == ["asphalt", "grass"]  # sand is not a trained terrain; the tile run ends before 3 s
    np.testing.assert_allclose(m, [[10 / 14, 0.0, 4 / 14], [0.0, 1.0, 0.0]])
    # two runs on one terrain pool by time: 7 s after 3 s above, and 7 s on grass in a run of ten 1 s cycles
    rows, m = top_terrain_confusion([("asphalt", t, on_asphalt), ("asphalt", t[:11] * 2, on_grass[:10])], names)
    np.testing.assert_allclose(m, [[5 / 14, 7 / 14, 2 / 14]])
    assert top_terrain_confusion([], names)[0] == []


def test_unknown_shares_on_trained_and_on_new_ground_and_the_delay() -> None:
    # 10 steps of 0.1 s: 4 on asphalt (trained), then 6 on glare ice (new), flagged from the 2nd step on it, and once
    # on asphalt
    times = np.arange(11) * 0.1
    driven = ["asphalt"] * 4 + ["glare_ice"] * 6
    p = np.array([0.0, 0.9, 0.0, 0.0, 0.1, 0.6, 0.9, 0.2, 0.8, 0.7])
    trained = ["asphalt", "grass", "tile"]
    assert unknown_share(times, p, driven, trained) == pytest.approx(0.25)  # false alarms: 1 of 4 steps
    assert unknown_share(times, p, driven, trained, new_ground=True) == pytest.approx(4 / 6)
    assert unknown_delay_s(times, p, driven, trained) == pytest.approx(0.1)
    assert unknown_share(times, p, ["asphalt"] * 10, trained, new_ground=True) is None  # no new ground driven
