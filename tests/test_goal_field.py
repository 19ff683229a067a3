"""The geodesic goal field: exact where the goal is in sight, close to the exact path length behind a circle,
and free of local minima in pockets where the straight-line distance has them."""

from __future__ import annotations

import numpy as np
import pytest

from gpmppi.mppi.bundles import K_GOAL_GEODESIC, N_COST_TERMS
from gpmppi.mppi.critics.goal import goal_term, straight_goal_cost
from gpmppi.mppi.goal_field import _STENCIL, GoalField, build_goal_field, goal_distance
from gpmppi.scenarios import PAPER_OBSTACLES


def _d(g: GoalField, x: float, y: float) -> float:
    return goal_distance(g.field, g.origin, g.inv_cell, x, y)


def _around_one_circle(p: np.ndarray, goal: np.ndarray, c: np.ndarray, r: float) -> float:
    """Exact shortest path from p to goal around one circle: two tangents and the arc between them."""
    dp, dg = np.linalg.norm(p - c), np.linalg.norm(goal - c)
    ang = np.arccos(np.clip(np.dot(p - c, goal - c) / (dp * dg), -1, 1))
    arc = ang - np.arccos(r / dp) - np.arccos(r / dg)
    return float(np.sqrt(dp**2 - r**2) + np.sqrt(dg**2 - r**2) + r * max(arc, 0.0))


def test_in_sight_the_field_is_the_straight_line_distance() -> None:
    goal = np.array([7.0, 5.0])
    g = build_goal_field(goal, PAPER_OBSTACLES, np.zeros((1, 2)))
    assert g.reachable
    # these points see the goal; bilinear interpolation of a smooth function: error ~ cell^2 / dist
    for p in [(4.0, 8.0), (7.0, 0.0), (9.0, 8.0), (9.5, 2.5)]:
        assert _d(g, *p) == pytest.approx(np.hypot(*(goal - p)), abs=2e-3)


def test_behind_a_circle_it_is_within_3_percent_of_the_exact_path() -> None:
    goal = np.array([10.0, 0.0])
    c, r = np.array([5.0, 0.0]), 1.5
    g = build_goal_field(goal, np.array([[c[0], c[1], r]]), np.array([[0.0, 0.0]]))
    rng = np.random.default_rng(4)
    errs = []
    for _ in range(200):
        p = np.array([rng.uniform(-2.0, 3.4), rng.uniform(-1.0, 1.0)])  # in the circle's shadow
        exact = _around_one_circle(p, goal, c, r)
        got = _d(g, *p)
        assert got >= exact - 0.01  # a grid path is never shorter than the true one (up to interpolation)
        errs.append((got - exact) / exact)
    assert max(errs) < 0.03


def test_no_local_minimum_in_the_pocket_between_overlapping_circles() -> None:
    goal = np.array([7.0, 5.0])
    g = build_goal_field(goal, PAPER_OBSTACLES, np.zeros((1, 2)))
    pocket = np.array([5.3, 4.2])  # between (5, 5) r .75 and (6, 4) r .85, which overlap: a dead end
    assert _d(g, *pocket) > np.hypot(*(goal - pocket)) + 1.5
    # steepest descent over the grid's own moves reaches the goal from every free cell, never climbing
    f = g.field[:, :, 0]
    h, w = f.shape
    cell = 1.0 / g.inv_cell
    ys = g.origin[1] + (np.arange(h) + 0.5) * cell
    xs = g.origin[0] + (np.arange(w) + 0.5) * cell
    gx, gy = np.meshgrid(xs, ys)
    free = np.ones((h, w), dtype=bool)
    for ox, oy, r in PAPER_OBSTACLES:
        free &= (gx - ox) ** 2 + (gy - oy) ** 2 >= r * r
    rng = np.random.default_rng(0)
    starts = np.argwhere(free)[rng.choice(int(free.sum()), 300, replace=False)]
    for i, j in starts:
        for _ in range(4 * (h + w)):
            if f[i, j] < 2 * cell:
                break
            moves = [(i + di, j + dj) for di, dj in _STENCIL if 0 <= i + di < h and 0 <= j + dj < w]
            ni, nj = min(moves, key=lambda m: f[m])
            assert f[ni, nj] < f[i, j], f"local minimum at ({xs[j]:.2f}, {ys[i]:.2f})"
            i, j = ni, nj
        assert f[i, j] < 2 * cell


def test_enclosed_goal_and_far_queries_stay_finite() -> None:
    goal = np.array([0.0, 0.0])
    ring = np.array([[2.0 * np.cos(a), 2.0 * np.sin(a), 0.8] for a in np.linspace(0, 2 * np.pi, 10, endpoint=False)])
    g = build_goal_field(goal, ring, np.array([[5.0, 0.0]]))
    assert np.all(np.isfinite(g.field))
    # from outside the ring no path reaches the goal: the value is above anything reachable inside it
    assert _d(g, 5.0, 0.0) > _d(g, 0.5, 0.0)
    # outside the grid: the edge value plus the way to it, so it keeps growing with distance
    assert np.isfinite(_d(g, 100.0, 0.0)) and _d(g, 100.0, 0.0) > _d(g, 50.0, 0.0) > _d(g, 5.0, 0.0)


def test_goal_term_selects_straight_line_or_field() -> None:
    goal = np.array([7.0, 5.0])
    g = build_goal_field(goal, PAPER_OBSTACLES, np.zeros((1, 2)))
    w = np.zeros(N_COST_TERMS)
    pocket = (5.3, 4.2)
    straight = straight_goal_cost(*pocket, goal, 2.0)
    assert goal_term(w, g.field, g.origin, g.inv_cell, goal, *pocket, 2.0) == pytest.approx(straight)
    w[K_GOAL_GEODESIC] = 1.0
    assert goal_term(w, g.field, g.origin, g.inv_cell, goal, *pocket, 2.0) == pytest.approx(2.0 * _d(g, *pocket))


def test_a_planners_plans_do_not_depend_on_fields_other_planners_built() -> None:
    """A fresh planner plans the same whatever another planner of the process planned the same scene from before
    (the shared field cache once kept the first caller's extent, so plans depended on the process's history)."""
    from cached_models import synthetic_model

    from gpmppi.mppi import goal_field
    from gpmppi.mppi.planner import Planner, PlannerConfig
    from gpmppi.mppi.recent import Recent
    from gpmppi.scenarios import paper_obstacle_scene

    sc = paper_obstacle_scene()
    cfg = PlannerConfig(dynamics="unicycle", backend="cpu", samples=64, seed=2)
    model = synthetic_model()

    def plans() -> list[bytes]:
        p, x, out = Planner(cfg, model), sc.start.copy(), []
        for _ in range(3):
            r = p.plan(x, sc.task, None)
            out.append(r.controls.tobytes() + np.float64(r.cost).tobytes())
            x = r.states[1].copy()
        return out

    goal_field._FIELDS = Recent()  # as in a fresh process
    alone = plans()
    goal_field._FIELDS = Recent()
    elsewhere = sc.start.copy()
    elsewhere[:2] += np.array([-6.0, 4.0])  # another planner first plans the scene from far off
    Planner(cfg, model).plan(elsewhere, sc.task, None)
    assert plans() == alone
