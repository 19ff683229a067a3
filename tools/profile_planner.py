"""Where one plan's time goes: `python -m tools.profile_planner [--samples S] [--horizon N] [--plans P] [--json]`.

The plan's own split (`PlanResult.timings_ms`: weights, tightening, rollouts, update, nominal scoring) of P plans of
the bench's GP planner (`tools.bench_planner`: circle lane, kinematic plant, fixed weights), and inside the rollouts
a copy of the CPU worker (`cpu_backend.rollout_worker`) with the CPU's cycle counter read around each phase, run on
one thread over the arguments of the last plan's rollouts: draw (the normals, `_unit_normals`, and the commands
made of them), GP rows requested (simplex corners and prefetch; with the table collapsed lazily, the ready box's
test too), GP rows read, the state advanced, the critics added (with the lane query alone, and each critic's term
alone, measured by loops of their own), and the lazy collapse (`ensure_slabs`: the lookups outside the ready box).
The copy's phases are the kernel's own compiled functions; only the loop around them is copied, so it reads the same
costs (checked: the copy's costs equal the kernel's bit for bit). For measuring, not for a plan.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from gpmppi.kernel_flags import FASTMATH, fetch_add
from gpmppi.mppi import backends, cpu_backend
from gpmppi.mppi.costs import advance_state, start_state, terminal_cost, weight_vector
from gpmppi.mppi.cpu_backend import (
    GROUP,
    _add_costs,
    _advance_group,
    _draw_commands,
    _ensure_cells,
    _lane_fields,
    _read_rows,
    _request_checked_rows,
    _request_rows,
    _thread_buffers,
    _unit_normals,
)
from gpmppi.mppi.critics.base import Step
from gpmppi.mppi.dynamics import DYN_GP, GP_SIMPLEX, velocity_coefficients
from gpmppi.mppi.gp_table import simplex_params
from gpmppi.mppi.lane import lane_field_at
from gpmppi.mppi.lazy_collapse import note_read, ready_box_of
from gpmppi.mppi.step import step_inputs

PHASES = ("ensure_slabs", "request_rows", "draw", "add_costs", "read_rows", "advance", "setup_terminal")


@intrinsic
def _cycles(typingctx):  # noqa: ANN001, ANN202 - numba intrinsic
    """The CPU's cycle counter (`llvm.readcyclecounter`: the TSC on x86, constant rate)."""
    def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
        fnty = ir.FunctionType(ir.IntType(64), [])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.readcyclecounter")
        return builder.call(fn, [])
    return types.uint64(), codegen


@njit(fastmath=FASTMATH, nogil=True)
def _profiled_worker(model: tuple, task: tuple, sampling: tuple, cost_w: np.ndarray, out: tuple, plan_consts: tuple,
                     work: tuple, ticks: np.ndarray, record: np.ndarray) -> None:
    """`cpu_backend.rollout_worker`'s loop with the cycle counter read around each phase (`PHASES` order); the
    simplex nodes of every sample's lookup of every step to `record` (samples, horizon, 5) when it has a row per
    sample (`tools.profile_lookup` counts the cache lines they touch), else (shape (0, 0, 5)) nowhere."""
    dyn_mode = model.dyn_mode
    gp_mode = model.gp_mode
    table = model.table
    tightened_hw = task.tightened_hw
    radii = task.radii
    x0 = sampling.x0
    nominal = sampling.nominal
    dt = sampling.dt
    seed = sampling.seed
    eps_out = out.eps_out
    cost_out = out.cost_out
    xy_out = out.xy_out
    coef, flat, next_group = plan_consts
    st, total, cmd_prev, cmd, cmd_next, res, nodes, node_w, noise, scratch, keys, seen, read, normals, lane = work
    samples = eps_out.shape[0]
    horizon = nominal.shape[0]
    n_xy = xy_out.shape[0]
    n_groups = (samples + GROUP - 1) // GROUP
    counter0 = sampling.iteration * samples
    inputs = step_inputs(model, sampling, sampling.noise_std, sampling.noise_memory, coef)
    dyn, limits = inputs.dyn, inputs.limits
    grid = simplex_params(model.dims, model.lo, model.inv_step)
    simplex = dyn_mode == DYN_GP and gp_mode == GP_SIMPLEX
    lazy = model.lazy
    lazy_collapse = simplex and lazy[0] != 0
    lazy_table = (lazy, model.table_src, model.collapse_w, table, model.dims)
    ready = ready_box_of(lazy)
    while True:
        g = fetch_add(next_group, 1)
        if g >= n_groups:
            break
        t = _cycles()
        first = g * GROUP
        n_in = min(GROUP, samples - first)
        for j in range(n_in):
            total[j] = 0.0
            for i in range(4):
                res[i, j] = 0.0
            for i in range(5):
                st[i, j] = x0[i]
            if first + j < n_xy:
                xy_out[first + j, 0, 0] = x0[0]
                xy_out[first + j, 0, 1] = x0[1]
        _draw_commands(seed, counter0, horizon, np.int64(0), limits, first, n_in, eps_out, cmd, noise, normals)
        state = start_state(cost_w)
        u = _cycles()
        ticks[6] += u - t
        for k in range(horizon):
            t = _cycles()
            outside = 0
            if lazy_collapse:
                outside = _request_checked_rows(grid, table, model.dims, ready, n_in, st, cmd, nodes, node_w, keys,
                                                read)
            elif simplex:
                _request_rows(grid, table, n_in, st, cmd, nodes, node_w)
            u = _cycles()
            ticks[1] += u - t
            if outside:
                _ensure_cells(lazy_table, n_in, keys, seen)
            t = _cycles()
            ticks[0] += t - u
            if simplex and record.shape[0] > 0:
                for j in range(n_in):
                    for q in range(5):
                        record[first + j, k, q] = nodes[q, j]
                t = _cycles()
            if k + 1 < horizon:
                _draw_commands(seed, counter0, horizon, k + 1, limits, first, n_in, eps_out, cmd_next, noise,
                               normals)
            u = _cycles()
            ticks[2] += u - t
            if k > 0:
                _add_costs(n_in, st, cmd_prev, res, total, cost_w, task, (tightened_hw[k], radii[k]), state, lane)
                state = advance_state(state, cost_w)
            t = _cycles()
            ticks[3] += t - u
            if simplex:
                _read_rows(n_in, flat, nodes, node_w, res)
            u = _cycles()
            ticks[4] += u - t
            _advance_group(dyn, dt, n_in, first, k, st, cmd, res, xy_out)
            t = _cycles()
            ticks[5] += t - u
            cmd_prev, cmd, cmd_next = cmd, cmd_next, cmd_prev
        t = _cycles()
        _add_costs(n_in, st, cmd_prev, res, total, cost_w, task, (tightened_hw[horizon], radii[horizon]), state,
                   lane)
        state = advance_state(state, cost_w)
        u = _cycles()
        ticks[3] += u - t
        for j in range(n_in):
            c = total[j] + terminal_cost(cost_w, task, tightened_hw[horizon], radii[horizon], state,
                                         (st[0, j], st[1, j], st[2, j], st[3, j], st[4, j]))
            if not np.isfinite(c):
                c = np.inf
            cost_out[first + j] = c
        ticks[6] += _cycles() - u
    if lazy_collapse:
        note_read(lazy, read[0], read[1], read[2], read[3], read[4], read[5])


@njit(nogil=True)
def _normals_only(seed: int, counter0: int, horizon: int, groups: int, normals: np.ndarray) -> np.uint64:
    """Cycles of every group's and step's normals alone (`_unit_normals`), as the worker draws them."""
    t = _cycles()
    for g in range(groups):
        for k in range(horizon):
            _unit_normals(seed, counter0, horizon, k, g * GROUP, GROUP, normals)
    return _cycles() - t


def _with_state(jit: object, term: object, slot: int) -> object:
    """`term` as the kernels' sum calls it: a stateful term (`slot` >= 0) gets its value from the step's state."""
    compiled = term  # already jitted, as registered
    if slot < 0:
        return compiled

    def one(w: float, cost_w: np.ndarray, pi: int, task: tuple, at: Step) -> float:
        return compiled(w, cost_w, pi, task, at, at.state[slot])

    return jit(one)


def _term_loop(term: object, wi: int, pi: int, slot: int) -> object:
    """A compiled loop of one critic's term over `reps` passes of a group's steps (cycles): the term alone, as
    the kernels' sum calls it (`_with_state` hands a stateful term its value)."""
    one = _with_state(njit(fastmath=FASTMATH, inline="always"), term, slot)

    @njit(fastmath=FASTMATH)
    def loop(reps: int, cost_w: np.ndarray, task: tuple, hw: float, radii: np.ndarray, state: tuple,
             st: np.ndarray, lane: np.ndarray, out: np.ndarray) -> np.uint64:
        t = _cycles()
        for _ in range(reps):
            for j in range(st.shape[1]):
                at = Step(st[0, j], st[1, j], st[2, j], st[3, j], st[4, j], st[3, j], st[4, j], 0.01, 0.01, hw, radii,
                          state, lane[0, j], lane[1, j], lane[2, j])
                out[j] += one(cost_w[wi], cost_w, pi, task, at)
        return _cycles() - t

    return loop


def _critic_split(model_task: tuple, cost_w: np.ndarray, groups: int, horizon: int, rate: float) -> dict[str, float]:
    """Each lane critic's term alone over as many steps as a plan's rollouts (its states: one group's first-step
    states, repeated) and the lane query's parts, [ms] on one thread: the term loops less an empty loop's
    time (building the step)."""
    from gpmppi.mppi.critics.registry import layout

    task, st, hw = model_task
    radii = np.zeros(0)
    state = advance_state(start_state(cost_w), cost_w)
    reps = groups * horizon
    lane = np.empty((4, GROUP))
    for j in range(GROUP):
        d, tx, ty, _exact = _field_one(task, st[0, j], st[1, j], hw)
        lane[0, j], lane[1, j], lane[2, j] = d, tx, ty
    out = np.zeros(GROUP)
    lay = layout()
    empty = _term_loop(_zero_term, 0, 0, -1)
    empty(1, cost_w, task, hw, radii, state, st, lane, out)
    base = min(empty(reps, cost_w, task, hw, radii, state, st, lane, out) for _ in range(5)) / rate
    split = {}
    for wi, pi, slot, term in lay.terms("lane", False):
        loop = _term_loop(term, wi, pi, slot)
        loop(1, cost_w, task, hw, radii, state, st, lane, out)
        split[lay.names[wi - lay.weight_index(lay.names[0])]] = max(
            0.0, min(loop(reps, cost_w, task, hw, radii, state, st, lane, out) for _ in range(5)) / rate - base)
    split["(building the step)"] = base
    split["lane query, grid part (`_lane_fields`)"] = min(
        _fields_loop(reps, task, hw, st, lane) for _ in range(5)) / rate
    return split


@njit(fastmath=FASTMATH, inline="always")
def _zero_term(weight: float, cost_w: np.ndarray, p: int, geo: tuple, at: tuple) -> float:
    return 0.0


@njit(fastmath=FASTMATH)
def _field_one(task: tuple, x: float, y: float, hw: float) -> tuple:
    return lane_field_at(task.field, task.origin, task.inv_cell, x, y, hw)


@njit
def _fields_loop(reps: int, task: tuple, hw: float, st: np.ndarray, lane: np.ndarray) -> np.uint64:
    t = _cycles()
    for _ in range(reps):
        _lane_fields(task, hw, GROUP, st, lane)
    return _cycles() - t


def _cycles_per_ms() -> float:
    """The cycle counter's rate, against `time.perf_counter` over 0.2 s."""
    c0, t0 = _cycles_now(), time.perf_counter()
    time.sleep(0.2)
    return (_cycles_now() - c0) / ((time.perf_counter() - t0) * 1e3)


@njit
def _cycles_now() -> np.uint64:
    return _cycles()


def _capture_rollout_args(samples: int, horizon: int, plans: int) -> tuple[tuple, list[dict[str, float]]]:
    """The bench's GP planner run `plans` plans in closed loop: each plan's `timings_ms`, and the arguments of the
    last plan's rollout kernel call."""
    from gpmppi.mppi.planner import PlannerConfig
    from tools.bench_planner import _load_model, _Ours

    model, _ = _load_model()
    m = len(model.terrains)
    weights = np.linspace(1.0, 2.0, m)
    weights /= weights.sum()
    ours = _Ours(PlannerConfig(samples=samples, horizon=horizon, backend="cpu"), model, weights)
    seen: list[tuple] = []
    kernel = backends.rollout_kernel

    def capture(*args: tuple) -> None:
        seen[:] = [args]
        kernel(*args)

    backends.rollout_kernel = capture
    try:
        for _ in range(plans):
            ours.step()
    finally:
        backends.rollout_kernel = kernel
    return seen[0], ours.phases_ms


def profile(samples: int, horizon: int, plans: int, repeats: int) -> dict:
    """The plan's split (p50 ms over `plans`, the first 5 left out) and the rollout phases' (one thread, the
    median of `repeats` runs over the last plan's arguments) [ms]."""
    args, phases_ms = _capture_rollout_args(samples, horizon, plans)
    model, task, sampling, cost, out = args
    kept = phases_ms[5:] or phases_ms
    plan_split = {name: float(np.percentile([t[name] for t in kept], 50)) for name in kept[0]}
    cost_w = weight_vector(cost)
    rate = _cycles_per_ms()
    runs = []
    cost_ref = out.cost_out.copy()
    for _ in range(repeats):
        plan_consts = (velocity_coefficients(model.theta, model.lateral), model.table.reshape(-1),
                       np.zeros(1, dtype=np.int64))
        ticks = np.zeros(len(PHASES), dtype=np.uint64)
        t0 = time.perf_counter()
        _profiled_worker(model, task, sampling, cost_w, out, plan_consts, _thread_buffers(model), ticks,
                         np.zeros((0, 0, 5), dtype=np.uint64))
        wall = (time.perf_counter() - t0) * 1e3
        runs.append((wall, ticks / rate))
    same = bool(np.array_equal(out.cost_out.view(np.uint64), cost_ref.view(np.uint64)))
    walls = [w for w, _ in runs]
    mid = runs[int(np.argsort(walls)[len(walls) // 2])]
    kernel_ms = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        cpu_backend.rollout_worker(model, task, sampling, cost_w, out,
                                   (velocity_coefficients(model.theta, model.lateral), model.table.reshape(-1),
                                    np.zeros(1, dtype=np.int64)), _thread_buffers(model))
        kernel_ms.append((time.perf_counter() - t0) * 1e3)
    groups = (samples + GROUP - 1) // GROUP
    normals = np.empty((2, GROUP))
    normals_ms = float(np.median([
        _normals_only(sampling.seed, sampling.iteration * samples, horizon, groups, normals) / rate
        for _ in range(repeats)]))
    critics = {}
    if out.xy_out.shape[0] > 0 and task.kind == 0:  # a lane task: its rollouts' first-step XY, repeated to a group
        states = np.resize(out.xy_out[:, 1, :], (GROUP, 2)).T
        st = np.zeros((5, GROUP))
        st[0:2] = states
        st[2] = np.arctan2(states[1], states[0]) + 0.5 * np.pi
        st[3] = 1.5
        st[4] = 0.2
        critics = _critic_split((task, st, float(task.tightened_hw[1])), cost_w, groups, horizon, rate)
    return {
        "critics_ms": critics,
        "samples": samples, "horizon": horizon, "plans": len(kept), "plan_p50_ms": plan_split,
        "rollout_one_thread_ms": float(np.median(kernel_ms)), "profiled_copy_ms": mid[0],
        "profiled_copy_costs_equal_kernel": same,
        "rollout_phases_ms": {name: float(v) for name, v in zip(PHASES, mid[1], strict=True)},
        "normals_alone_ms": normals_ms,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=1024)
    p.add_argument("--horizon", type=int, default=40)
    p.add_argument("--plans", type=int, default=60)
    p.add_argument("--repeats", type=int, default=21)
    p.add_argument("--json", action="store_true")
    a = p.parse_args()
    res = profile(a.samples, a.horizon, a.plans, a.repeats)
    if a.json:
        print(json.dumps(res))
        return
    print(f"S={a.samples} N={a.horizon}, p50 of {res['plans']} plans [ms]: "
          + ", ".join(f"{k} {v:.3f}" for k, v in res["plan_p50_ms"].items()))
    print(f"rollouts on one thread: kernel {res['rollout_one_thread_ms']:.3f} ms, profiled copy "
          f"{res['profiled_copy_ms']:.3f} ms (costs equal: {res['profiled_copy_costs_equal_kernel']})")
    for name, ms in res["rollout_phases_ms"].items():
        print(f"  {name:15s} {ms:7.3f} ms")
    print(f"  (normals alone {res['normals_alone_ms']:.3f} ms of draw)")
    if res["critics_ms"]:
        print("the lane critics' terms alone over the same number of steps (one thread):")
        for name, ms in res["critics_ms"].items():
            print(f"  {name:15s} {ms:7.3f} ms")


if __name__ == "__main__":
    main()
