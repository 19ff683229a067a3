"""Obstacles from an occupancy grid: the distance the costmap critic reads and its chance-constrained radius against
brute-force references, the critic's cost in the CPU kernel and the CUDA simulator's against a brute-force score of
the same rollouts, map_server map files, and the goal field routing around the grid's walls."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from costmap_case import case_grid
from costmap_case import run as run_case
from cuda_mode import cuda_env

from gpmppi.costmap import Costmap, CostmapError, lethal_radius, load_map_yaml, rasterise_circles, write_map
from gpmppi.mppi.costs import ChanceQuantiles
from gpmppi.mppi.critics.costmap import grid_lookup
from gpmppi.mppi.goal_field import build_goal_field, goal_distance
from gpmppi.scenarios import ScenarioFileError, load_scene

REPO = Path(__file__).resolve().parents[1]


def test_interpolated_distance_is_within_a_cell_of_the_brute_force_distance() -> None:
    grid = case_grid()
    arrays, frame = grid.kernel_arrays()
    rng = np.random.default_rng(0)
    corners = grid.corners()
    pts = rng.uniform(corners.min(0), corners.max(0), size=(3000, 2))
    looked = [grid_lookup(arrays, frame, float(x), float(y)) for x, y in pts]
    inside = np.array([a[0] for a in looked])
    d = np.array([a[1] for a in looked])
    ref = grid.nearest_lethal(pts)
    g = grid.to_grid(pts)
    h, w = grid.shape
    expect_inside = (g[:, 0] >= 0) & (g[:, 1] >= 0) & (g[:, 0] < w) & (g[:, 1] < h)
    assert np.array_equal(inside, expect_inside) and inside.sum() > 1000
    # the distance is 1-Lipschitz: between the four nearest cell centres (each within a cell's diagonal) the
    # interpolation errs by at most that diagonal; measured it is far less on average
    err = np.abs(d[inside] - ref[inside])
    assert err.max() <= np.sqrt(2.0) * grid.resolution
    assert err.mean() < 0.2 * grid.resolution
    # the cell's value as a fraction of the lethal threshold (unknown: 0)
    cells = np.floor(g[inside]).astype(int)
    value = np.array([a[2] for a in looked])[inside]
    expect = np.clip(grid.values[cells[:, 1], cells[:, 0]] / 100.0, 0.0, 1.0)
    assert np.allclose(value, expect, atol=1e-6)


def _brute_force_costs(out: dict, grid: Costmap) -> tuple[np.ndarray, np.ndarray, float]:
    """Each rollout's costmap cost from its points by brute force (distance to every lethal cell centre), as the
    least and the most it can be: a point within the interpolation's error (a cell's diagonal) of its step's radius
    may be scored either way; and the share of points scored without that doubt."""
    xy = np.asarray(out["xy"])
    radii = np.asarray(out["radii"])
    low = np.zeros(xy.shape[0])
    high = np.zeros(xy.shape[0])
    sure = 0
    h, w = grid.shape
    for k in range(1, xy.shape[1]):  # the state after step k - 1 is scored with bound k
        p = xy[:, k]
        g = grid.to_grid(p)
        inside = (g[:, 0] >= 0) & (g[:, 1] >= 0) & (g[:, 0] < w) & (g[:, 1] < h)
        d = grid.nearest_lethal(p)
        cells = np.floor(g).astype(int)
        value = np.zeros(p.shape[0])
        value[inside] = np.clip(grid.values[cells[inside, 1], cells[inside, 0]] / 100.0, 0.0, 1.0)
        graded = np.where(inside, out["weight"] * out["value_scale"] * value, 0.0)
        doubt = inside & (np.abs(d - radii[k]) <= np.sqrt(2.0) * grid.resolution)
        hit = inside & (d < radii[k]) & ~doubt
        low += np.where(hit, out["weight"], np.where(doubt, np.minimum(graded, out["weight"]), graded))
        high += np.where(hit | doubt, out["weight"], graded)
        sure += int(np.count_nonzero(~doubt))
    return low, high, sure / (xy.shape[0] * (xy.shape[1] - 1))


def _check_case(out: dict) -> None:
    grid = case_grid()
    # the chance constraint: robot radius + half a cell's diagonal + Phi^-1(p) sqrt(lambda_max(Sigma_XY)), capped
    q = ChanceQuantiles.for_probability(0.95).normal
    lam = np.array([np.linalg.eigvalsh(np.asarray(c)[:2, :2]).max() for c in out["covs"]])
    expect = lethal_radius(out["robot_radius"], grid.resolution) + np.minimum(q * np.sqrt(lam), 1.0)
    # (the planner's default step clearance then adds half a step's travel in quadrature)
    half_step = 0.5 * 0.1 * 2.0
    assert np.allclose(out["radii"], np.sqrt(expect**2 + half_step**2), rtol=1e-12)
    assert out["radii"][-1] > out["radii"][1] > out["radii"][0]
    low, high, sure = _brute_force_costs(out, grid)
    costs = np.asarray(out["costs"])
    assert sure > 0.8, sure
    assert np.all(costs >= low - 1e-4) and np.all(costs <= high + 1e-4)
    exact = low == high
    assert exact.sum() >= 10 and np.allclose(costs[exact], low[exact], rtol=1e-5, atol=1e-5)
    assert (low >= out["weight"]).sum() >= 3  # some rollouts surely hit the lethal cells
    assert (high < out["weight"]).sum() >= 3  # and some surely did not


def test_the_cpu_kernel_scores_the_grid_as_the_brute_force_reference() -> None:
    _check_case(run_case("cpu"))


@pytest.mark.slow(seconds=5)  # the CUDA simulator runs the kernel as Python
def test_the_cuda_kernel_scores_the_grid_as_the_brute_force_reference(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, str(REPO / "tests" / "costmap_case.py"), "cuda"], cwd=REPO,
                          env=cuda_env(PYTHONWARNINGS="ignore::RuntimeWarning"), capture_output=True, text=True,
                          timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.split("RESULT ", 1)[1])
    _check_case(out)
    cpu = run_case("cpu")
    assert np.allclose(out["costs"], cpu["costs"], rtol=1e-6)  # the same noise, so the same rollouts


def test_map_server_files_round_trip_and_bad_ones_are_refused(tmp_path: Path) -> None:
    grid = case_grid()
    values = np.where(grid.values >= 100, 100, np.where(grid.values < 0, -1, 0)).astype(np.int16)
    trinary = Costmap(values, 0.05, (1.5, -2.0, 0.0))
    write_map(trinary, tmp_path / "m.yaml", "m.pgm")
    back = load_map_yaml(tmp_path / "m.yaml")
    assert np.array_equal(back.values, values) and back.resolution == 0.05 and back.origin == (1.5, -2.0, 0.0)
    # negate: white is occupied
    text = (tmp_path / "m.yaml").read_text().replace("negate: 0", "negate: 1")
    (tmp_path / "n.yaml").write_text(text)
    neg = load_map_yaml(tmp_path / "n.yaml")
    assert np.array_equal(neg.values == 100, values != 100)  # white free and grey unknown: both read as dark
    (tmp_path / "short.pgm").write_bytes((tmp_path / "m.pgm").read_bytes()[:-10])
    (tmp_path / "s.yaml").write_text(text.replace("m.pgm", "short.pgm"))
    with pytest.raises(CostmapError, match=r"short\.pgm: \d+ pixels for 80 x 80; the file is cut short"):
        load_map_yaml(tmp_path / "s.yaml")
    (tmp_path / "p.yaml").write_text(text.replace("m.pgm", "m.png"))
    with pytest.raises(CostmapError, match="only PGM images are read"):
        load_map_yaml(tmp_path / "p.yaml")
    scene = tmp_path / "scene_m.yaml"
    scene.write_text("start: {x: 0, y: 0}\ngoal: [1, 1]\nmap: missing.yaml\n")
    with pytest.raises(ScenarioFileError, match="field 'map': map file .*missing.yaml: not found"):
        load_scene(scene)


def test_the_goal_field_routes_around_the_grids_wall() -> None:
    # a wall across x = 2 m from y = -3 to 3 m, the way round it over its ends
    values = np.zeros((160, 120), dtype=np.int16)
    res = 0.05
    values[20:140, 60:62] = 100  # x 3.0-3.1 m over the grid's origin (-1, -4): world x 2.0-2.1, y -3..3
    grid = Costmap(values, res, (-1.0, -4.0, 0.0))
    goal = np.array([4.0, 0.0])
    field = build_goal_field(goal, np.zeros((0, 3)), np.array([[0.0, 0.0]]), margin=1.0, cell=0.1, costmap=grid,
                             clearance=0.2)
    d = goal_distance(field.field, field.origin, field.inv_cell, 0.0, 0.0)
    around = 2 * np.hypot(2.05, 3.0 + lethal_radius(0.2, res))  # over an end of the wall and back
    assert d > 1.2 * 4.0  # not the straight line through the wall
    assert d == pytest.approx(around, rel=0.06)


def test_a_scene_with_a_map_loads_its_grid() -> None:
    scene = load_scene(REPO / "gpmppi" / "data" / "scene_rooms.yaml")
    grid = scene.task.costmap
    assert grid is not None and grid.lethal_cells.any()
    assert grid.clearance(scene.start[None, :2], 0.3)[0] > 0.0


def test_the_paper_scene_rasterised_covers_its_circles() -> None:
    from gpmppi.scenarios import PAPER_OBSTACLES

    grid = rasterise_circles(PAPER_OBSTACLES, 0.05, np.array([-1.0, -1.0]), np.array([9.0, 7.0]))
    rng = np.random.default_rng(1)
    pts = rng.uniform([-1, -1], [9, 7], size=(4000, 2))
    d_circle = (np.linalg.norm(pts[:, None] - PAPER_OBSTACLES[None, :, :2], axis=2) - PAPER_OBSTACLES[:, 2]).min(1)
    clear = grid.clearance(pts)
    # inside a circle is inside the grid's obstacles; farther than a cell's diagonal from every circle is clear
    assert np.all(clear[d_circle < -0.5 * np.sqrt(2) * 0.05] < 0.0)
    assert np.all(clear[d_circle > 2 * np.sqrt(2) * 0.05] > 0.0)
