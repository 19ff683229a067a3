"""CPU backend: a serial kernel, one per thread, runs every sample's whole horizon (noise, model, GP, costs).

Each thread takes groups of `GROUP` samples from a shared counter and steps them in lockstep over the horizon
(`rollout_kernel`, `rollout_worker`; docs/development.md says why it is built this way).

The kernel takes the five bundles of `gpmppi.mppi.bundles` (their `.args()` tuples).

Each sample draws its noise from the counter-based generator (`rng.normal_pair`), so the result
is identical whatever the thread schedule. Per sample it writes the applied perturbation (the
clipped control minus the nominal one, float32), its total cost, and for the first `xy_out.shape[0]`
samples the XY of the rollout.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit

from gpmppi.kernel_flags import FASTMATH, fetch_add, phase, prefetch_row, row_axpy, vector_phase
from gpmppi.mppi.costs import (
    advance_state,
    lane_stage_cost_at,
    plain_stage_cost,
    stage_reads_lane,
    start_state,
    terminal_cost,
    weight_vector,
)
from gpmppi.mppi.dynamics import DYN_GP, GP_SIMPLEX, advance, gp_residual, velocity_coefficients
from gpmppi.mppi.gp_table import cell32, simplex_corner, simplex_params
from gpmppi.mppi.lane import lane_distance, lane_field_at
from gpmppi.mppi.lazy_collapse import block_keys, empty_box, ensure_block_at, note_read, ready_box_of
from gpmppi.mppi.rng import command_from_normals, normal_pair
from gpmppi.mppi.step import step_inputs
from gpmppi.mppi.worker_pool import WorkerPool

__all__ = ["GROUP", "rollout_kernel", "rollout_worker"]

# samples a thread steps in lockstep: each sample's step waits on its own GP table reads (the next
# state needs them), so interleaving independent samples lets those memory reads overlap, and the vector loops (the
# noise, the simplex corners) run longer. 64 since 2026-12-04: the kernel 3-4% faster than at 32, 6% at 128 (but
# S = 1024 is then only 8 groups for the threads to share out); a sample's result does not depend on it
GROUP = 64


@vector_phase
def _unit_normals(seed: int, counter0: int, horizon: int, k: int, first: int, n_in: int, normals: np.ndarray) -> None:
    """Step k's standard normals of the group's samples first .. first + n_in - 1 (`rng.normal_pair`) into `normals`
    (2, GROUP).

    A phase of its own, free of anything but the generator's arithmetic, and a `vector_phase` (the generator never
    divides by less than 1.7), so that it compiles to vector code: 8 samples at a time, about half the time of a
    sample at a time."""
    for j in range(n_in):
        z0, z1 = normal_pair(seed, (counter0 + first + j) * horizon + k)
        normals[0, j] = z0
        normals[1, j] = z1


@phase
def _draw_commands(
    seed: int, counter0: int, horizon: int, k: int, limits: tuple, first: int, n_in: int, eps_out: np.ndarray,
    cmd: np.ndarray, noise: np.ndarray, normals: np.ndarray,
) -> None:
    """Step k's noisy commands of the group's samples first .. first + n_in - 1 into `cmd`; perturbations to eps_out.

    `counter0` = iteration * samples (the noise counter of sample s, step k is (counter0 + s) * horizon + k);
    `limits` = (nominal, noise_std, u_lo, u_hi, (noise memory, innovation), (command in effect, rate step));
    `noise` holds each sample's unit noise of step k - 1 and gets step k's (`rng.sampled_command`); `normals` is
    a work buffer (2, GROUP) for the step's standard normals."""
    nominal, noise_std, u_lo, u_hi, ar, first_step = limits
    _unit_normals(seed, counter0, horizon, k, first, n_in, normals)
    for j in range(n_in):
        s = first + j
        u0, u1, d0, d1 = command_from_normals(normals[0, j], normals[1, j], nominal, k, noise_std, u_lo, u_hi, ar,
                                              noise[0, j], noise[1, j], first_step)
        noise[0, j] = d0
        noise[1, j] = d1
        eps_out[s, k, 0] = u0 - nominal[k, 0]
        eps_out[s, k, 1] = u1 - nominal[k, 1]
        cmd[0, j] = u0
        cmd[1, j] = u1


@vector_phase
def _lane_fields(task: tuple, threshold: float, n_in: int, st: np.ndarray, lane: np.ndarray) -> None:
    """Each sample's lane query from the grid alone (`lane.lane_field_at`) into `lane` (4, GROUP): distance,
    direction (tx, ty), and 1 where the exact distance must replace the distance. A loop free of calls and
    branches (vector code; its one division, by the lane grid's cells per metre, is never by zero)."""
    field = task.field
    origin = task.origin
    inv_cell = task.inv_cell
    for j in range(n_in):
        d, tx, ty, exact = lane_field_at(field, origin, inv_cell, st[0, j], st[1, j], threshold)
        lane[0, j] = d
        lane[1, j] = tx
        lane[2, j] = ty
        lane[3, j] = 1.0 if exact else 0.0


@phase
def _add_costs(
    n_in: int, st: np.ndarray, cmd: np.ndarray, res: np.ndarray, total: np.ndarray, cost_w: np.ndarray, task: tuple,
    bounds: tuple, state: tuple, lane: np.ndarray,
) -> None:
    """Add one step's stage cost to each sample's total: states `st` after the step, its commands and GP variances;
    `bounds` = (this step's tightened half-width, its inflated radii), `state` the stateful critics' values of the
    step (`costs.start_state`); `lane` (4, GROUP) a work buffer for a lane task's lane queries.

    A lane task's lane queries first, from the grid in a loop of their own (vector code), then the few exact
    distances they need, then the critics: the same values as `costs.stage_cost`'s query per sample, in a third
    of the time."""
    tightened_hw, radii = bounds
    if stage_reads_lane(task.kind):
        _lane_fields(task, tightened_hw, n_in, st, lane)
        for j in range(n_in):
            if lane[3, j] != 0.0:
                lane[0, j] = lane_distance(task.seg, task.cell_start, task.candidates, task.origin, task.inv_cell,
                                           task.field.shape[1], task.field.shape[0], st[0, j], st[1, j])
        for j in range(n_in):
            total[j] += lane_stage_cost_at(cost_w, task, tightened_hw, radii, state,
                                           (st[0, j], st[1, j], st[2, j], st[3, j], st[4, j]), (cmd[0, j], cmd[1, j]),
                                           (res[2, j], res[3, j]), (lane[0, j], lane[1, j], lane[2, j]))
        return
    for j in range(n_in):
        total[j] += plain_stage_cost(cost_w, task, tightened_hw, radii, state,
                                     (st[0, j], st[1, j], st[2, j], st[3, j], st[4, j]), (cmd[0, j], cmd[1, j]),
                                     (res[2, j], res[3, j]))


@phase
def _ensure_cells(lazy_table: tuple, n_in: int, keys: np.ndarray, seen: np.ndarray) -> None:
    """Make current the table slabs of this step's lookups outside the ready box (a lazily collapsed table, `keys`
    from `_request_checked_rows`: each lookup's `block_key`, -1 inside the box) through their cell's stamp
    (`lazy_collapse.ensure_block_at`), once per cell and thread in this plan (`seen` marks the cells checked)."""
    lazy, src, collapse_w, table, dims = lazy_table
    for j in range(n_in):
        b = keys[j]
        if b >= 0 and seen[b] == 0:
            ensure_block_at(lazy, src, collapse_w, table, dims, b)
            seen[b] = 1


@phase
def _request_rows(
    grid: tuple, table: np.ndarray, n_in: int, st: np.ndarray, cmd: np.ndarray, nodes: np.ndarray, node_w: np.ndarray,
) -> None:
    """The simplex nodes and weights of each sample's GP input, and a prefetch of their table rows: the rows
    arrive from memory while the next commands are drawn and the last step's costs added."""
    # a loop of its own, free of the noise's library calls and of branches, so that it is vectorised
    for j in range(n_in):
        n0, t0, t1, t2, t3, w0, w1, w2, w3, w4 = simplex_corner(grid, st[3, j], st[4, j], cmd[0, j], cmd[1, j])
        nodes[0, j] = n0
        nodes[1, j] = n0 + t0
        nodes[2, j] = n0 + t0 + t1
        nodes[3, j] = n0 + t0 + t1 + t2
        nodes[4, j] = n0 + t0 + t1 + t2 + t3
        node_w[0, j] = w0
        node_w[1, j] = w1
        node_w[2, j] = w2
        node_w[3, j] = w3
        node_w[4, j] = w4
    for j in range(n_in):
        for q in range(5):
            prefetch_row(table, nodes[q, j])


@phase
def _request_checked_rows(
    grid: tuple, table: np.ndarray, dims: np.ndarray, ready: tuple, n_in: int, st: np.ndarray, cmd: np.ndarray,
    nodes: np.ndarray, node_w: np.ndarray, keys: np.ndarray, read: np.ndarray,
) -> int:
    """`_request_rows` on a lazily collapsed table, with the lazy collapse's box test in the same loop: whether each
    lookup's cell lies in the ready box `ready` (lo0, hi0, lo1, hi1, lo2, hi2 as int32,
    `lazy_collapse.in_ready_box`), where its slabs are current. `keys` gets each lookup's `block_key` outside the box
    and -1 inside it, `read` (int64 lo0, hi0, lo1, hi1, lo2, hi2) the box of every cell the thread's lookups read
    (`lazy_collapse.note_read`). Returns the number of lookups outside the box (`_ensure_cells` then makes their slabs
    current, before the rows are read).

    The test is a few compares on the cell indices the corners compute anyway (the same `cell32` calls, computed
    once), so a step whose lookups all lie in the box costs no check of its own: as a phase of its own (a call per
    step, its loop computing the cells again, and its constants set up per call) it took 0.08 ms a plan on one
    thread."""
    lo0, lo1, lo2, _l3, inv0, inv1, inv2, _i3, top0, top1, top2, _t3, last0, last1, last2, _a3, _s0, _s1, _s2 = grid
    in0, ix0, in1, ix1, in2, ix2 = ready
    d1 = np.int32(dims[1])
    d2 = np.int32(dims[2])
    r0 = np.int32(read[0])
    x0 = np.int32(read[1])
    r1 = np.int32(read[2])
    x1 = np.int32(read[3])
    r2 = np.int32(read[4])
    x2 = np.int32(read[5])
    outside = np.int32(0)
    # a loop of its own, free of the noise's library calls and of branches, so that it is vectorised
    for j in range(n_in):
        n0, t0, t1, t2, t3, w0, w1, w2, w3, w4 = simplex_corner(grid, st[3, j], st[4, j], cmd[0, j], cmd[1, j])
        nodes[0, j] = n0
        nodes[1, j] = n0 + t0
        nodes[2, j] = n0 + t0 + t1
        nodes[3, j] = n0 + t0 + t1 + t2
        nodes[4, j] = n0 + t0 + t1 + t2 + t3
        node_w[0, j] = w0
        node_w[1, j] = w1
        node_w[2, j] = w2
        node_w[3, j] = w3
        node_w[4, j] = w4
        i0, _f0 = cell32(st[3, j], lo0, inv0, top0, last0)
        i1, _f1 = cell32(st[4, j], lo1, inv1, top1, last1)
        i2, _f2 = cell32(cmd[0, j], lo2, inv2, top2, last2)
        out = (i0 < in0) | (i0 > ix0) | (i1 < in1) | (i1 > ix1) | (i2 < in2) | (i2 > ix2)
        keys[j] = (i0 * d1 + i1) * d2 + i2 if out else np.int32(-1)
        outside += np.int32(out)
        r0 = i0 if i0 < r0 else r0
        x0 = i0 if i0 > x0 else x0
        r1 = i1 if i1 < r1 else r1
        x1 = i1 if i1 > x1 else x1
        r2 = i2 if i2 < r2 else r2
        x2 = i2 if i2 > x2 else x2
    read[0] = r0
    read[1] = x0
    read[2] = r1
    read[3] = x1
    read[4] = r2
    read[5] = x2
    for j in range(n_in):
        for q in range(5):
            prefetch_row(table, nodes[q, j])
    return outside


@phase
def _read_rows(n_in: int, flat: np.ndarray, nodes: np.ndarray, node_w: np.ndarray, res: np.ndarray) -> None:
    """Each sample's GP residual [mean_v, mean_w, var_v, var_w]: its five table rows, weighted, a row at a time
    (`row_axpy`: one load and one multiply-add of four values; the same sums, in the same order, as four scalar
    chains)."""
    four = np.uint64(4)  # flat offsets, unsigned: no negative-index wrap-around and no multiply by the row length
    for j in range(n_in):
        c = row_axpy(None, node_w[0, j], flat, four * nodes[0, j])
        for q in range(1, 5):
            c = row_axpy(c, node_w[q, j], flat, four * nodes[q, j])
        res[0, j] = c[0]
        res[1, j] = c[1]
        res[2, j] = c[2]
        res[3, j] = c[3]


@phase
def _gp_residuals(gp: tuple, scratch: tuple, n_in: int, st: np.ndarray, cmd: np.ndarray, res: np.ndarray) -> None:
    """Each sample's GP residual by `gp_residual` (multilinear grid or exact GP)."""
    for j in range(n_in):
        res[0, j], res[1, j], res[2, j], res[3, j] = gp_residual(gp, scratch, cmd[0, j], cmd[1, j], st[3, j],
                                                                 st[4, j])


@phase
def _advance_group(
    dyn: tuple, dt: float, n_in: int, first: int, k: int, st: np.ndarray, cmd: np.ndarray, res: np.ndarray,
    xy_out: np.ndarray,
) -> None:
    """Step every sample's state; the first `xy_out.shape[0]` samples' XY to `xy_out`.

    The GP model's step in a loop of its own, with the mode a constant there and no other store than the states:
    free of branches and of checked divisions, it compiles to vector code (the loop over every mode, with the
    rollouts' XY stored in it, ran a sample at a time). The XY are copied after, for the samples that keep them."""
    dyn_mode, coef, edd5_p = dyn
    if dyn_mode == DYN_GP:
        for j in range(n_in):
            px, py, yaw, v, w = advance(DYN_GP, dt, coef, edd5_p, (st[0, j], st[1, j], st[2, j], st[3, j], st[4, j]),
                                        (cmd[0, j], cmd[1, j]), res[0, j], res[1, j])
            st[0, j] = px
            st[1, j] = py
            st[2, j] = yaw
            st[3, j] = v
            st[4, j] = w
    else:
        for j in range(n_in):
            px, py, yaw, v, w = advance(dyn_mode, dt, coef, edd5_p,
                                        (st[0, j], st[1, j], st[2, j], st[3, j], st[4, j]), (cmd[0, j], cmd[1, j]),
                                        res[0, j], res[1, j])
            st[0, j] = px
            st[1, j] = py
            st[2, j] = yaw
            st[3, j] = v
            st[4, j] = w
    for j in range(min(n_in, xy_out.shape[0] - first)):
        xy_out[first + j, k + 1, 0] = st[0, j]
        xy_out[first + j, k + 1, 1] = st[1, j]


@njit(cache=True, fastmath=FASTMATH, nogil=True, _nrt=False)
def rollout_worker(
    model: tuple, task: tuple, sampling: tuple, cost_w: np.ndarray, out: tuple, plan_consts: tuple, work: tuple,
) -> None:
    """Roll out sample groups until none is left; several threads may run it at once (`rollout_kernel`).

    The bundles' tuples as `gpmppi.mppi.bundles` defines them (`.args()`), the cost bundle as its weight vector
    (`weight_vector`). `plan_consts` = (the model's `velocity_coefficients`, its GP table as one run of floats,
    the shared group counter): each group of `GROUP` samples is taken from the counter (1-D int64, from 0;
    `fetch_add`). `work` = this thread's buffers (`_thread_buffers`).

    Serial, without the GIL and without reference counting (`_nrt=False`: it allocates nothing, so it needs
    none): numba's `parallel=True` passes took ~70% of this kernel's compile time, and the reference counts of
    the arrays handed to the per-step phases cost more than the phases' work. The phases are functions of
    their own, each compiled once."""
    # every field is read here, once, outside the sample loops: read from the tuples inside them the kernel ran
    # slower and its results differed in the last bits
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
    dyn, limits, gp = inputs.dyn, inputs.limits, inputs.gp
    dims = model.dims
    grid = simplex_params(dims, model.lo, model.inv_step)
    simplex = dyn_mode == DYN_GP and gp_mode == GP_SIMPLEX
    lazy = model.lazy
    lazy_collapse = simplex and lazy[0] != 0
    lazy_table = (lazy, model.table_src, model.collapse_w, table, dims)
    ready = ready_box_of(lazy)
    while True:
        g = fetch_add(next_group, 1)
        if g >= n_groups:
            break
        first = g * GROUP
        n_in = min(GROUP, samples - first)
        for j in range(n_in):
            total[j] = 0.0
            for i in range(4):
                res[i, j] = 0.0  # GP residual [mean_v, mean_w, var_v, var_w]; stays zero for the other models
            for i in range(5):
                st[i, j] = x0[i]
            if first + j < n_xy:
                xy_out[first + j, 0, 0] = x0[0]
                xy_out[first + j, 0, 1] = x0[1]
        # step 0 as an int64, not the literal 0: numba would compile the phase a second time for `Literal[int](0)`
        _draw_commands(seed, counter0, horizon, np.int64(0), limits, first, n_in, eps_out, cmd, noise, normals)
        state = start_state(cost_w)  # the stateful critics' values of step k - 1
        # Step k: (1) the GP table rows of step k are requested (prefetch), (2) the next step's commands are
        # drawn and (3) the previous step's cost is added, both needing no table, while the rows arrive from
        # memory, (4) the rows are read, (5) the states advance. Costs are added in step order.
        for k in range(horizon):
            if lazy_collapse:  # the rows requested and the lookups outside the ready box made current
                if _request_checked_rows(grid, table, dims, ready, n_in, st, cmd, nodes, node_w, keys, read):
                    _ensure_cells(lazy_table, n_in, keys, seen)
            elif simplex:
                _request_rows(grid, table, n_in, st, cmd, nodes, node_w)
            if k + 1 < horizon:
                _draw_commands(seed, counter0, horizon, k + 1, limits, first, n_in, eps_out, cmd_next, noise,
                               normals)
            if k > 0:
                _add_costs(n_in, st, cmd_prev, res, total, cost_w, task, (tightened_hw[k], radii[k]), state, lane)
                state = advance_state(state, cost_w)
            if simplex:
                _read_rows(n_in, flat, nodes, node_w, res)
            elif dyn_mode == DYN_GP:
                _gp_residuals(gp, scratch, n_in, st, cmd, res)
            _advance_group(dyn, dt, n_in, first, k, st, cmd, res, xy_out)
            cmd_prev, cmd, cmd_next = cmd, cmd_next, cmd_prev
        _add_costs(n_in, st, cmd_prev, res, total, cost_w, task, (tightened_hw[horizon], radii[horizon]), state,
                   lane)
        state = advance_state(state, cost_w)
        for j in range(n_in):
            t = total[j] + terminal_cost(cost_w, task, tightened_hw[horizon], radii[horizon], state,
                                         (st[0, j], st[1, j], st[2, j], st[3, j], st[4, j]))
            if not np.isfinite(t):
                t = np.inf
            cost_out[first + j] = t
    if lazy_collapse:
        note_read(lazy, read[0], read[1], read[2], read[3], read[4], read[5])


def _thread_buffers(model: tuple) -> tuple:
    """One thread's buffers for `rollout_worker`: a group's states, totals, the commands of the previous, this and
    the next step (rotated every step), GP residuals, simplex node indices and weights (one row per vertex:
    unit-stride rows let the loop that fills them run as vector code), the unit noise of the last step drawn, and
    the exact GP's work arrays, (`_request_checked_rows`, `_ensure_cells`) the lookups' cell keys, the cells whose
    table slabs this thread made current and the box of the cells it read, (`_unit_normals`) the standard normals of
    the step being drawn, and (`_add_costs`) a lane task's lane queries."""
    n_tasks, n_train = model.ex_alpha.shape
    dims = model.dims
    return (np.empty((5, GROUP)), np.empty(GROUP), np.empty((2, GROUP)), np.empty((2, GROUP)), np.empty((2, GROUP)),
            np.zeros((4, GROUP)), np.zeros((5, GROUP), dtype=np.uint64), np.zeros((5, GROUP), dtype=np.float32),
            np.zeros((2, GROUP)), (np.empty(n_train), np.empty(n_tasks), np.empty(n_tasks)),
            np.zeros(GROUP, dtype=np.int32), np.zeros(block_keys(dims), dtype=np.uint8), empty_box(),
            np.empty((2, GROUP)), np.empty((4, GROUP)))


def rollout_kernel(model: tuple, task: tuple, sampling: tuple, cost: tuple, out: tuple) -> None:
    """Every sample's rollout and total cost (the bundles' tuples, `gpmppi.mppi.bundles`, `.args()`): `rollout_worker`
    on this thread and on `numba.get_num_threads() - 1` pool threads, which share out the sample groups."""
    samples = out.eps_out.shape[0]
    n_groups = (samples + GROUP - 1) // GROUP
    threads = max(1, min(numba.get_num_threads(), n_groups))
    plan_consts = (velocity_coefficients(model.theta, model.lateral), model.table.reshape(-1),
                   np.zeros(1, dtype=np.int64))
    head = (model, task, sampling, weight_vector(cost), out, plan_consts)
    calls = [(*head, _thread_buffers(model)) for _ in range(threads)]
    if threads == 1:
        rollout_worker(*calls[0])
        return
    _POOL.run(rollout_worker, calls)


_POOL = WorkerPool()  # the pool threads of every plan in this process

