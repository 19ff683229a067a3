"""Lane direction and the along-lane speed term; per-task control noise; the state estimate's covariance."""

from __future__ import annotations

import numpy as np
import pytest
from cached_models import synthetic_model

from gpmppi.mppi.bundles import N_COST_TERMS, TaskBundle
from gpmppi.mppi.costs import stage_cost
from gpmppi.mppi.critics.registry import layout
from gpmppi.mppi.lane import LaneLookup, build_lane_lookup, lane_query
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.scenarios import circle_lane, paper_obstacle_scene, square_lane


def _query(lane: LaneLookup, x: float, y: float, threshold: float = 10.0) -> tuple[float, float, float]:
    return lane_query(lane.segments, lane.cell_start, lane.candidates, lane.field, lane.origin, lane.inv_cell, x, y,
                      threshold)


def test_direction_follows_the_point_order_of_the_polyline() -> None:
    sq = square_lane()  # counter-clockwise: +x along y=0, +y along x=20, -x along y=20, -y along x=0
    lane = build_lane_lookup(sq.task.centerline, True, margin=3.0)
    for (x, y), t in [((10.0, 0.3), (1, 0)), ((19.6, 10.0), (0, 1)), ((10.0, 21.0), (-1, 0)), ((-0.5, 7.0), (0, -1))]:
        _, tx, ty = _query(lane, x, y)
        assert (tx, ty) == pytest.approx(t, abs=1e-9)
    # a reversed polyline drives the other way
    rev = build_lane_lookup(sq.task.centerline[::-1], True, margin=3.0)
    assert _query(rev, 10.0, 0.3)[1:] == pytest.approx((-1.0, 0.0), abs=1e-9)
    # on a circle it is the counter-clockwise tangent, to the polygon's chord accuracy
    ci = circle_lane()
    lane_c = build_lane_lookup(ci.task.centerline, True, margin=3.0)
    rng = np.random.default_rng(0)
    for a in rng.uniform(0, 2 * np.pi, 50):
        r = 8.25 + rng.uniform(-1.5, 1.5)
        _, tx, ty = _query(lane_c, r * np.cos(a), r * np.sin(a))
        assert tx * -np.sin(a) + ty * np.cos(a) > np.cos(np.deg2rad(2.0))


def test_direction_turns_smoothly_across_a_corner_bisector_and_stays_bounded_off_grid() -> None:
    lane = build_lane_lookup(square_lane().task.centerline, True, margin=3.0, cell=0.1)
    # inside the corner at (20, 0) the nearest segment switches on the diagonal x - 20 = -y
    along = np.linspace(-0.3, 0.3, 61)
    dirs = np.array([_query(lane, 19.0 + s, 1.0 + s)[1:] for s in along])  # crosses the bisector at s = 0
    assert dirs[0] == pytest.approx((1.0, 0.0), abs=1e-9) and dirs[-1] == pytest.approx((0.0, 1.0), abs=1e-9)
    assert np.all(np.abs(np.diff(dirs, axis=0)) < 0.75)  # no jump larger than one cell's blend
    # far outside the lookup grid the direction is that of the nearest edge cell (finite, at most unit length)
    d, tx, ty = _query(lane, 80.0, -50.0)
    assert np.isfinite(d) and np.hypot(tx, ty) <= 1.0 + 1e-12


def test_direction_turns_over_two_metres_of_arc_around_a_corner() -> None:
    # the chord over 1 m of arc either side of the projection: the sides' own directions from 1 m on, the bisector at
    # the vertex, rotating in between, so a rollout turning into the corner earns speed along the lane there
    lane = build_lane_lookup(square_lane().task.centerline, True, margin=3.0, cell=0.1)
    assert _query(lane, 18.95, 0.0)[1:] == pytest.approx((1.0, 0.0), abs=1e-9)  # 1.05 m before the corner (20, 0)
    assert _query(lane, 20.0, 1.05)[1:] == pytest.approx((0.0, 1.0), abs=1e-9)  # 1.05 m after it
    # (to the blend of the four cell centres around the point)
    assert _query(lane, 20.0, 0.0)[1:] == pytest.approx((2 ** -0.5, 2 ** -0.5), abs=0.02)
    _, tx, ty = _query(lane, 19.5, 0.0)  # 0.5 m before: the chord from (18.5, 0) to (20, 0.5)
    assert (tx, ty) == pytest.approx(np.array([1.5, 0.5]) / np.hypot(1.5, 0.5), abs=0.02)
    # an open lane's ends keep the end segments' directions
    open_lane = build_lane_lookup(np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0]]), False, margin=2.0, cell=0.1)
    assert _query(open_lane, 0.05, 0.0)[1:] == pytest.approx((1.0, 0.0), abs=1e-9)
    assert _query(open_lane, 5.0, 4.95)[1:] == pytest.approx((0.0, 1.0), abs=1e-9)


def _lane_step_cost(lane: LaneLookup, yaw: float, along: bool) -> float:
    w = np.zeros(N_COST_TERMS)
    w[layout().weight_index("speed")] = 1.0
    w[layout().param_index("speed", "along_lane")] = float(along)
    task = TaskBundle.for_lane(lane, 2.75, np.full(2, 2.75), 1.5).args()
    return stage_cost(w, task, 2.75, np.zeros(0), (1.0,), (10.0, 0.0, yaw, 1.5, 0.0), (1.5, 0.0), (0.0, 0.0))


def test_speed_term_counts_speed_along_the_lane_only() -> None:
    lane = build_lane_lookup(square_lane().task.centerline, True, margin=3.0)
    # at 1.5 m/s with target 1.5: forward costs nothing, backwards (2 * 1.5)^2, sideways 1.5^2
    assert _lane_step_cost(lane, 0.0, True) == pytest.approx(0.0, abs=1e-12)
    assert _lane_step_cost(lane, np.pi, True) == pytest.approx(9.0)
    assert _lane_step_cost(lane, np.pi / 2, True) == pytest.approx(2.25)
    # the paper's form: the speed magnitude, whatever the heading
    assert _lane_step_cost(lane, np.pi, False) == pytest.approx(0.0, abs=1e-12)


def test_lane_tasks_sample_with_the_lane_noise_and_goals_with_noise_std() -> None:
    model = synthetic_model()
    cfg = PlannerConfig(samples=32, horizon=6, backend="cpu", dynamics="unicycle", lane_noise_std=(0.0, 0.0),
                        noise_std=(0.5, 0.5), initial_control=(1.0, 0.0))
    lane_sc, goal_sc = circle_lane(), paper_obstacle_scene()
    lane = Planner(cfg, model).plan(lane_sc.start, lane_sc.task)
    goal = Planner(cfg, model).plan(goal_sc.start, goal_sc.task)
    assert np.ptp(lane.sample_states, axis=0).max() == 0.0  # no noise: every rollout is the nominal one
    assert np.ptp(goal.sample_states, axis=0).max() > 0.01
    both = Planner(cfg.model_copy(update={"lane_noise_std": None}), model).plan(lane_sc.start, lane_sc.task)
    assert np.ptp(both.sample_states, axis=0).max() > 0.01  # None: lanes use noise_std too


def test_state_covariance_starts_the_propagation_and_inflates_the_first_steps() -> None:
    model = synthetic_model()
    sc = paper_obstacle_scene()
    base = {"samples": 32, "horizon": 5, "backend": "cpu", "step_clearance": False, "seed": 3}
    zero = Planner(PlannerConfig(state_std=(0.0,) * 5, **base), model).plan(sc.start, sc.task)
    std = (0.02, 0.01, 0.003, 0.008, 0.01)
    est = Planner(PlannerConfig(state_std=std, **base), model).plan(sc.start, sc.task)
    np.testing.assert_allclose(est.covariances[0], np.diag(np.square(std)), rtol=0, atol=1e-15)
    assert np.all(zero.covariances[0] == 0.0)
    # step 0: radius + Phi^-1(0.95) sqrt(n^T S n), n from each obstacle centre to the start
    obs = sc.task.obstacles
    n = (sc.start[:2] - obs[:, :2]) / np.linalg.norm(sc.start[:2] - obs[:, :2], axis=1)[:, None]
    s2 = n[:, 0] ** 2 * std[0] ** 2 + n[:, 1] ** 2 * std[1] ** 2
    np.testing.assert_allclose(est.tightened[0], obs[:, 2] + 1.6448536269514722 * np.sqrt(s2), rtol=1e-9)
    np.testing.assert_allclose(zero.tightened[0], obs[:, 2], rtol=1e-12)
    # a covariance handed to plan() replaces the configured one
    given = np.diag([0.04, 0.04, 0.0, 0.0, 0.0]) ** 2
    r = Planner(PlannerConfig(**base), model).plan(sc.start, sc.task, state_cov=given)
    np.testing.assert_allclose(r.covariances[0], given, atol=1e-15)


@pytest.mark.parametrize("bad", [np.eye(4), np.full((5, 5), np.nan), -np.eye(5)])
def test_bad_state_covariance_is_rejected(bad: np.ndarray) -> None:
    sc = paper_obstacle_scene()
    planner = Planner(PlannerConfig(samples=16, horizon=3, backend="cpu"), synthetic_model())
    with pytest.raises(ValueError, match="state_cov"):
        planner.plan(sc.start, sc.task, state_cov=bad)


def test_lane_query_distance_is_exact_at_the_threshold_and_close_elsewhere() -> None:
    from gpmppi.mppi.lane import brute_force_distance

    lane = build_lane_lookup(square_lane().task.centerline, True, margin=3.0, cell=0.1)
    rng = np.random.default_rng(5)
    for x, y, thr in zip(rng.uniform(-5, 25, 3000), rng.uniform(-5, 25, 3000), rng.uniform(0.1, 2.75, 3000),
                         strict=True):
        d = _query(lane, x, y, thr)[0]
        ref = brute_force_distance(lane.segments, x, y)
        assert (d > thr) == (ref > thr)
        assert abs(d - ref) <= np.sqrt(2) * 0.1 + 1e-9
