"""Seeded plans do not depend on what was compiled before the planner's kernels, nor on the numba cache's state.

Why separate processes: numba compiles a function once per process, and with `cache=True` it loads
a function compiled by an earlier process from disk instead. A function the kernel calls but does
not inline is then linked into the kernel either as IR compiled in this process (which LLVM can
inline and optimise together with the kernel's fastmath code) or as object code from the cache
(which it cannot): the kernel's machine code, and so its results, depended on what had been compiled
and cached before it. This happened with `velocity_coefficients` before it was inlined: closed-loop
results changed with the cache's history (with it un-inlined, this test fails). Within one process
that history is fixed after the first compilation, so only fresh processes with their own cache
folders can show it:

- `plan` in an empty cache: the planner's kernels and everything they call are compiled fresh;
- `helpers` in a second empty cache: compiles the kernels' helper functions on their own (dynamics,
  GP lookup, noise, costs, lane, grid interpolation) and caches them, without planning; then
  `other_first` in that cache calls those helpers first (now loaded from the cache) and plans, so
  its kernels are compiled against cached helpers;
- `plan` again in the second cache: every kernel is loaded from the cache;
- `other_first` in a third, empty cache: the helpers and the delay predictor compiled in the process
  before the kernels. With the 'contract' fastmath flag this order alone changed the kernels' last bits.

Each planning run does 10 seeded iterations of the EDD5, unicycle and GP models on the circle lane,
feeding back the first step of the nominal trajectory, and prints every control sequence and cost
as exact hex; all runs must print the same bytes.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

SCRIPT = r"""
import sys
import numpy as np

if sys.argv[1] in ("helpers", "other_first"):
    from gpmppi.costs import N_COST_WEIGHTS, lane_exit_cost, slip_cost, stage_cost, tighten_lane, variance_cost
    from gpmppi.gp.grid_interp import grid_interp
    from gpmppi.models.dynamic_unicycle import nominal_step, jacobian
    from gpmppi.mppi.dynamics import advance, nominal_velocity_step, velocity_coefficients
    from gpmppi.mppi.gp_table import interp4, interp4_simplex, simplex_nodes
    from gpmppi.mppi.lane import build_lane_lookup, lane_query
    from gpmppi.mppi.rng import noisy_command, normal_pair

    theta = np.array([0.3, 0.25, 0.1, 1.0, 0.05, 1.1])
    x = np.array([0.1, 0.2, 0.3, 0.8, 0.1])
    u = np.array([1.0, 0.2])
    coef = velocity_coefficients(theta, np.array([-0.05, -0.02]))
    nominal_velocity_step(coef, 0.5, 0.1, 1.0, 0.2, 0.1)
    advance(2, 0.1, coef, np.ones(5), 0.0, 0.0, 0.1, 0.5, 0.1, 1.0, 0.2, 0.01, 0.02)
    nominal_step(theta, x, u, 0.1)
    jacobian(theta, x, u, 0.1)
    table = np.ones((81, 4), dtype=np.float32)
    dims = np.array([3, 3, 3, 3])
    simplex_nodes(dims, np.zeros(4), np.ones(4), 0.5, 0.5, 0.5, 0.5)
    interp4_simplex(table, dims, np.zeros(4), np.ones(4), 0.5, 0.5, 0.5, 0.5)
    interp4(table, dims, np.zeros(4), np.ones(4), 0.5, 0.5, 0.5, 0.5)
    grid_interp(np.ones((3, 3, 3, 3, 2)), np.zeros(4), np.ones(4), np.full(4, 0.5), np.zeros(2))
    normal_pair(1, 2)
    noisy_command(1, 2, np.ones((3, 2)), 0, np.ones(2), np.zeros(2), np.full(2, 2.0))
    variance_cost(0.1, 0.2, 1.0)
    slip_cost(0.5, 0.1, 1.0, 0.2, 1.0)
    lane_exit_cost(1.0, 1.5, 0.9, 1.0)
    tighten_lane(np.zeros((3, 5, 5)), 1.0, 5.99, 0.2)
    lane = build_lane_lookup(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]), False, 1.0)
    lane_query(lane.segments, lane.cell_start, lane.candidates, lane.field, lane.origin, lane.inv_cell, 0.5, 0.1,
               0.5)
    stage_cost(0, np.ones(N_COST_WEIGHTS), lane.segments, lane.cell_start, lane.candidates, lane.field, lane.origin,
               lane.inv_cell, 1.0, 0.8, 1.0, np.zeros(2), np.zeros((0, 3)), np.zeros(0), 1.0, 0.5, 0.1, 0.3, 0.5,
               0.1, 1.0, 0.2, 0.01, 0.02)
    # the delay predictor (its own kernel over the same helpers) compiled first: with the 'contract' fastmath flag
    # this history alone changed the rollout kernel's last bits
    from gpmppi.gp.model_file import load_default_model
    from gpmppi.mppi.dynamics import DYN_UNICYCLE, predict_ahead
    from gpmppi.mppi.planner import Planner, PlannerConfig

    pl = Planner(PlannerConfig(dynamics="unicycle"), load_default_model())
    tw = np.full(3, 1.0 / 3.0)
    edd5_p, _ = pl._terrain_setup(tw)
    predict_ahead(np.zeros(5), np.eye(5), np.array([1.0, 0.5]), 0.25, 0.1, DYN_UNICYCLE, pl._theta, pl._lateral,
                  edd5_p, pl._gp_mode, pl._table, pl._table_dims, pl._grid_lo, pl._grid_inv, *pl._ex, tw)
    if sys.argv[1] == "helpers":
        sys.exit(0)

from gpmppi.gp.model_file import load_default_model
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.scenarios import circle_lane

model = load_default_model()
sc = circle_lane()
w = np.array([0.5, 0.3, 0.2])
for dyn in ("edd5", "unicycle", "gp"):
    p = Planner(PlannerConfig(dynamics=dyn, backend="cpu", samples=256, seed=7), model)
    x = sc.start.copy()
    for _ in range(10):
        r = p.plan(x, sc.task, w)
        print(dyn, r.controls.tobytes().hex(), np.float64(r.cost).tobytes().hex())
        x = r.states[1].copy()
"""


def _run(mode: str, cache: Path) -> subprocess.Popen:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    return subprocess.Popen([sys.executable, "-c", SCRIPT, mode], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _output(proc: subprocess.Popen) -> str:
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err[-3000:]
    assert out.count("\n") == 30, out[-500:]
    return out


def test_plans_do_not_depend_on_compile_order_or_cache(tmp_path: Path) -> None:
    fresh_cache, other_cache = tmp_path / "fresh", tmp_path / "other"
    # the fresh compilation runs beside the other chain (compilation dominates the time)
    fresh = _run("plan", fresh_cache)
    helpers = _run("helpers", other_cache)
    _, err = helpers.communicate(timeout=300)
    assert helpers.returncode == 0, err[-3000:]
    assert any(other_cache.rglob("*.nbi")), "compiling the helpers wrote no numba cache"
    out_fresh = _output(fresh)
    # helpers and the delay predictor compiled in this process before the kernels, in an empty cache
    out_other_order = _output(_run("other_first", tmp_path / "other_order"))
    out_other_first = _output(_run("other_first", other_cache))
    out_from_cache = _output(_run("plan", other_cache))
    assert out_other_order == out_fresh
    assert out_other_first == out_fresh
    assert out_from_cache == out_fresh
