"""Seeded plans and closed loops do not depend on what was compiled before the planner's kernels, nor on the numba
cache's state.

Why separate processes: numba compiles a function once per process, and with `cache=True` it loads
a function compiled by an earlier process from disk instead. A function the kernel calls but does
not inline is then linked into the kernel either as IR compiled in this process (which LLVM can
inline and optimise together with the kernel's fastmath code) or as object code from the cache
(which it cannot): the kernel's machine code, and so its results, depended on what had been compiled
and cached before it. This happened with `velocity_coefficients` before it was inlined: closed-loop
results changed with the cache's history (with it un-inlined, this test fails). Within one process
that history is fixed after the first compilation, so only fresh processes with their own cache
folders can show it. Four histories:

- empty cache: `plan` compiles the planner's kernels and everything they call fresh;
- helpers first, in an empty cache: `helpers_first` compiles the kernels' helper functions on their own
  (dynamics, GP lookup, noise, costs, lane, grid interpolation; among them those the kernels link rather than
  inline, with the kernels' own types: the GP residual, the model step, the Jacobian, the split critics), the
  delay predictor (its own kernel over the same helpers) and then the rollout kernel (one unicycle plan) before
  its closed loop. With the 'contract' fastmath flag this order alone changed the kernels' last bits;
- helpers cached: the same process copies its cache folder once the helpers are compiled (so that copy holds
  the helpers and no kernel); `helpers_first` in that copy loads the helpers from disk and compiles the
  kernels against them: they link the GP residual, the model step, the Jacobian and the split critics as
  object code from the cache, the case of `velocity_coefficients` below (until 2026-12-07 those were compiled
  with other types in the helpers' section, so this case compiled them again, ~12 CPU s, and linked none);
- fully cached: `plan` in the first case's cache loads every kernel from disk.

The first case compiles in one process (`GPMPPI_COMPILE_AHEAD=0`) and with numba's inliner as shipped (it copies
a callee's IR block by block, `gpmppi.kernel_flags._copy_inlined_ir_with_one_scope` with one scope); the two
helpers-first cases compile the rollout kernel in a second process while the first compiles the rest
(`gpmppi.mppi.compile_ahead`, the default on a cold cache) and load it from the cache. Each case prints how its
process got the rollout kernel (compiled, loaded), and the test checks that each history was the one meant.

Each run first drives a closed loop (GP-MPPI on the physics plant, terrain weights moving every cycle, the
command latency predicted ahead), which in an empty cache compiles the kernels in the order the services do; a
difference in the last bit grows there from cycle to cycle. It prints every cycle's command and weights. Then it
does 10 seeded iterations of the EDD5, unicycle and GP models on the circle lane, feeding back the first step of
the nominal trajectory, and prints every control sequence and cost. All as exact hex; all runs must print the
same bytes.

With the `reassoc` fastmath flag a closed loop differed from its seventh cycle on when the delay predictor and
a plan had been compiled first: numba names the variables of inlined functions with process-wide counters and orders
some of its passes by those names, so the IR that reaches LLVM is ordered differently after a different history,
and `reassoc` lets LLVM regroup a floating-point sum by that order (see `gpmppi/kernel_flags.py`).

Compilation dominates the time, so the cases run side by side, each as soon as the cache it needs exists.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

HELPERS_CACHED = "helpers compiled and cached"
KERNEL = "rollout kernel:"
LINKED = "linked helpers compiled:"
LOOP_S = 3.0  # [s] of closed loop: 30 planner cycles
PLAN_LINES = 30 + 30  # the closed loop's cycles, then 3 models x 10 iterations

SCRIPT = r"""
import sys
import numpy as np

HELPERS_CACHED = "@HELPERS_CACHED@"
KERNEL = "@KERNEL@"
LINKED = "@LINKED@"
LOOP_S = @LOOP_S@

if sys.argv[1] == "helpers_first":
    from gpmppi.mppi.bundles import CRITICS, N_COST_TERMS
    from gpmppi.mppi.costs import stage_cost, tighten_lane
    from gpmppi.mppi.critics import lane_exit, slip, variance
    from gpmppi.gp.grid_interp import grid_interp
    from gpmppi.models.dynamic_unicycle import nominal_step, jacobian_into
    from gpmppi.mppi.dynamics import advance, nominal_velocity_step, velocity_coefficients
    from gpmppi.mppi.gp_table import interp4, interp4_simplex, simplex_nodes
    from gpmppi.mppi.lane import build_lane_lookup, lane_query
    from gpmppi.mppi.rng import normal_pair, sampled_command

    theta = np.array([0.3, 0.25, 0.1, 1.0, 0.05, 1.1])
    x = np.array([0.1, 0.2, 0.3, 0.8, 0.1])
    u = np.array([1.0, 0.2])
    coef = velocity_coefficients(theta, np.array([-0.05, -0.02]))
    nominal_velocity_step(coef, 0.5, 0.1, 1.0, 0.2, 0.1)
    advance(2, 0.1, coef, np.ones(5), (0.0, 0.0, 0.1, 0.5, 0.1), (1.0, 0.2), 0.01, 0.02)
    nominal_step(theta, x, u, 0.1)
    jacobian_into(np.eye(5), theta, x, u, 0.1, 0.0, 0.0, 0.0, 0.0)  # as `propagate` calls it
    table = np.ones((81, 4), dtype=np.float32)
    dims = np.array([3, 3, 3, 3])
    simplex_nodes(dims, np.zeros(4), np.ones(4), 0.5, 0.5, 0.5, 0.5)
    interp4_simplex(table, dims, np.zeros(4), np.ones(4), 0.5, 0.5, 0.5, 0.5)
    interp4(table, dims, np.zeros(4), np.ones(4), 0.5, 0.5, 0.5, 0.5)
    grid_interp(np.ones((3, 3, 3, 3, 2)), np.zeros(4), np.ones(4), np.full(4, 0.5), np.zeros(2))
    normal_pair(1, 2)
    sampled_command(1, 2, np.ones((3, 2)), 1, np.ones(2), np.zeros(2), np.full(2, 2.0), (0.5, 0.75**0.5), 0.1, 0.2,
                    (np.ones(2), np.full(2, np.inf)))
    from gpmppi.mppi.critics.base import Step

    step = Step(0.0, 0.0, 0.1, 0.5, 0.1, 1.0, 0.2, 0.1, 0.2, 1.5, np.zeros(0), (0.9,), 1.0, 1.0, 0.0)
    for term in (variance.variance_cost, slip.slip_cost):
        term(1.0, np.ones(N_COST_TERMS), 0, (), step)
    lane_exit.lane_exit_cost(1.0, np.ones(N_COST_TERMS), 0, (), step, 0.9)
    tighten_lane(np.zeros((3, 5, 5)), 1.0, 5.99, 0.2)
    lane = build_lane_lookup(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]), False, 1.0)
    lane_query(lane.segments, lane.cell_start, lane.candidates, lane.field, lane.origin, lane.inv_cell, 0.5, 0.1,
               0.5)
    from gpmppi.mppi.bundles import TaskBundle

    task = TaskBundle.for_lane(lane, 1.0, np.full(3, 0.8), 1.0).args()
    stage_cost(np.ones(N_COST_TERMS), task, 0.8, np.zeros(0), (1.0,), (0.5, 0.1, 0.3, 0.5, 0.1), (1.0, 0.2),
               (0.01, 0.02))
    # the helpers the serial kernels call rather than inline (the GP residual, the model step, the Jacobian above, the
    # split critics), with the kernels' own types: the kernels compiled after them link them, and the helpers-cached
    # case links them loaded from its copy of this cache
    from gpmppi.gp.model_file import load_default_model
    from gpmppi.mppi.costs import stage_critics, start_state, terminal_critics, weight_vector
    from gpmppi.mppi.dynamics import dyn_inputs, gp_inputs, gp_residual, gp_scratch, predict_ahead, step_state
    from gpmppi.mppi.planner import Planner, PlannerConfig
    from gpmppi.scenarios import circle_lane

    pl = Planner(PlannerConfig(dynamics="unicycle"), load_default_model())
    tw = np.full(3, 1.0 / 3.0)
    bundle = pl.terrain.set_weights(tw)
    model = bundle.args()
    # their arguments as the kernels build them, by the builders' Python (compiled, they would be three more
    # functions of this history: every case compiles them inlined)
    gp, scratch = gp_inputs.py_func(model), gp_scratch.py_func(model)
    gp_residual(gp, scratch, 1.0, 0.2, 0.5, 0.1)
    step_state(dyn_inputs.py_func(model, coef), gp, scratch, 0.1, (0.0, 0.0, 0.1, 0.5, 0.1), (1.0, 0.2), 1.0)
    cost_w = weight_vector(pl.kind(circle_lane().task).cost.args())
    split = np.zeros(len(CRITICS))
    stage_critics(cost_w, task, 0.8, np.zeros(0), start_state(cost_w), (0.5, 0.1, 0.3, 0.5, 0.1), (1.0, 0.2),
                  (0.01, 0.02), split)
    terminal_critics(cost_w, task, 0.8, np.zeros(0), start_state(cost_w), (0.5, 0.1, 0.3, 0.5, 0.1), split)
    if len(sys.argv) > 2:  # a copy of the cache as it is now: the helpers compiled, no planner kernel yet
        import os
        import shutil

        shutil.copytree(os.environ["NUMBA_CACHE_DIR"], sys.argv[2] + ".partial")
        os.rename(sys.argv[2] + ".partial", sys.argv[2])
    print(HELPERS_CACHED, flush=True)
    # the delay predictor (its own kernel over the same helpers) compiled first, called as the planner calls it: with
    # the 'contract' fastmath flag this history alone changed the rollout kernel's last bits
    predict_ahead(model, np.zeros(5), np.eye(5), np.array([1.0, 0.5]), 0.25, 0.1, 0.0, 0.0)
    # and one plan, so that the rollout kernel is compiled before the closed loop's estimator and plant: with the
    # 'reassoc' fastmath flag this history changed the closed loop from its seventh cycle
    pl.plan(circle_lane().start.copy(), circle_lane().task, tw)

from dataclasses import replace

from gpmppi.evaluation.closed_loop import run_closed_loop
from gpmppi.evaluation.runner import EvalSettings, Job, cached_gp_model, loop_config, make_planner, make_plant
from gpmppi.gp.model_file import load_default_model
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.scenarios import circle_lane
from gpmppi.terrain.least_squares import TerrainEstimator

# first a closed loop, so that in an empty cache it compiles the kernels in its own order (the estimator's exact GP,
# the delay predictor, the rollouts): GP-MPPI on the tile circle, weights moving every cycle, one cycle of command
# latency predicted ahead; its small differences grow from cycle to cycle
sc = circle_lane()
settings = EvalSettings(latency_s=0.1, samples=256)
job = Job(kind="tracking", scenario=sc, terrain="tile", dynamics="gp", seeds=(0,))
cfg = replace(loop_config(settings, job), time_limit_s=LOOP_S)
model = cached_gp_model(None)
traj = run_closed_loop(make_planner(settings, "gp", "tile", 0), make_plant(settings, "tile", 0), sc.task, sc.start,
                       model.n_terrains, cfg, estimator=TerrainEstimator(model))
for k in range(traj.commands.shape[0]):
    print("loop", k, traj.commands[k].tobytes().hex(), traj.weights[k].tobytes().hex())

model = load_default_model()
w = np.array([0.5, 0.3, 0.2])
for dyn in ("edd5", "unicycle", "gp"):
    p = Planner(PlannerConfig(dynamics=dyn, backend="cpu", samples=256, seed=7), model)
    x = sc.start.copy()
    for _ in range(10):
        r = p.plan(x, sc.task, w)
        print(dyn, r.controls.tobytes().hex(), np.float64(r.cost).tobytes().hex())
        x = r.states[1].copy()

from gpmppi.models.dynamic_unicycle import jacobian_into
from gpmppi.mppi.costs import stage_critics, terminal_critics
from gpmppi.mppi.cpu_backend import rollout_worker
from gpmppi.mppi.dynamics import gp_residual, step_state

# which of the helpers the kernels link this process compiled (the helpers-cached case: none), and how it got the
# rollout kernel: compiled it, or loaded it from the cache
linked = (gp_residual, step_state, jacobian_into, stage_critics, terminal_critics)
print(LINKED, " ".join(sorted(f.py_func.__name__ for f in linked if f._cache_misses)))
print(KERNEL, "compiled" if rollout_worker._cache_misses else "loaded" if rollout_worker._cache_hits else "unused")
"""


@dataclass
class Case:
    """One case of SCRIPT running in its own process; its log (stderr) goes to a file, so no pipe fills up."""

    proc: subprocess.Popen
    log: Path


# numba's inliner as shipped: its own `copy` module back (`gpmppi.kernel_flags._copy_inlined_ir_with_one_scope`)
NUMBAS_OWN_IR_COPIES = "import copy, gpmppi.kernel_flags, numba.core.inline_closurecall as m; m.copy = copy\n"


def start_case(mode: str, cache: Path, copy_helpers_cache_to: Path | None = None, ahead: bool = True) -> Case:
    """One case of SCRIPT in a fresh process whose numba cache is `cache`: mode `plan` or `helpers_first`;
    `copy_helpers_cache_to` (helpers_first only): where to copy the cache once the helpers are compiled; `ahead`:
    whether a cold rollout kernel is compiled in a second process (`gpmppi.mppi.compile_ahead`); without it, with
    numba's inliner as shipped too."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), GPMPPI_COMPILE_AHEAD="1" if ahead else "0")
    script = (("" if ahead else NUMBAS_OWN_IR_COPIES) + SCRIPT.replace("@HELPERS_CACHED@", HELPERS_CACHED)
              .replace("@KERNEL@", KERNEL).replace("@LINKED@", LINKED).replace("@LOOP_S@", repr(LOOP_S)))
    args = [sys.executable, "-c", script, mode]
    if copy_helpers_cache_to is not None:
        args.append(str(copy_helpers_cache_to))
    log = cache.with_name(f"{cache.name}-{mode}-{time.monotonic_ns()}.log")
    with log.open("w") as err:
        proc = subprocess.Popen(args, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=err, text=True)
    return Case(proc, log)


def wait_helpers_cached(case: Case) -> None:
    """Wait until a helpers_first case has compiled (and copied) its helpers' cache."""
    assert case.proc.stdout is not None
    line = case.proc.stdout.readline()
    if line.strip() != HELPERS_CACHED:
        case.proc.wait(timeout=60)
        raise AssertionError(f"helpers_first printed {line!r} before its helpers were cached: "
                             f"{case.log.read_text()[-3000:]}")


ALL_LINKED = "gp_residual jacobian_into stage_critics step_state terminal_critics"


def case_output(case: Case, kernel: str, linked: str) -> str:
    """The case's plans (hex lines) once it has finished; its process must have got the rollout kernel as
    `kernel` says (compiled, loaded), and compiled the helpers the kernels link that `linked` names (all of them,
    `ALL_LINKED`, or none: the helpers-cached case loads them, so the helpers' section must compile them with the
    kernels' types)."""
    out, _ = case.proc.communicate(timeout=1800)  # compiling on a loaded machine takes long
    assert case.proc.returncode == 0, case.log.read_text()[-3000:]
    rest, _, how = out.replace(HELPERS_CACHED + "\n", "").rpartition(KERNEL)
    plans, _, compiled = rest.rpartition(LINKED)
    assert how.strip() == kernel, f"the rollout kernel was {how.strip()!r} in this process, not {kernel!r}"
    assert compiled.strip() == linked, f"this process compiled the linked helpers {compiled.strip()!r}, not {linked!r}"
    assert plans.count("\n") == PLAN_LINES, out[-500:]
    return plans


def same(out: str, reference: str, history: str) -> None:
    """Fail naming the first line (a closed-loop cycle or a plan) where a history's output differs."""
    for line, ref in zip(out.splitlines(), reference.splitlines(), strict=True):
        assert line == ref, f"{history} changed the output from\n  {ref}\nto\n  {line}"


@pytest.mark.slow(seconds=130)  # three compilations of the planner's kernels, each in its own process
@pytest.mark.timeout(2400)  # the compilations share the machine: on a loaded one they take long
def test_plans_do_not_depend_on_compile_order_or_cache(tmp_path: Path) -> None:
    empty, helpers_first, helpers_cached = tmp_path / "empty", tmp_path / "helpers_first", tmp_path / "helpers_cached"
    cases: list[Case] = []
    try:
        cases.append(fresh := start_case("plan", empty, ahead=False))
        cases.append(other_order := start_case("helpers_first", helpers_first, copy_helpers_cache_to=helpers_cached))
        wait_helpers_cached(other_order)
        assert any(helpers_cached.rglob("*.nbi")), "compiling the helpers wrote no numba cache"
        cases.append(other_first := start_case("helpers_first", helpers_cached))
        out_fresh = case_output(fresh, "compiled", ALL_LINKED)
        cases.append(from_cache := start_case("plan", empty))
        same(case_output(other_order, "loaded", ALL_LINKED), out_fresh, "the helpers and delay predictor compiled "
             "first, the rollout kernel in a second process, numba's inliner with one scope per copy")
        same(case_output(other_first, "loaded", ""), out_fresh, "kernels compiled against cached helpers, the rollout "
             "kernel in a second process, numba's inliner with one scope per copy")
        same(case_output(from_cache, "loaded", ""), out_fresh, "kernels loaded from the cache")
    finally:  # a failed or timed-out case leaves no compiling process behind
        for case in cases:
            if case.proc.poll() is None:
                case.proc.kill()
                case.proc.wait()
