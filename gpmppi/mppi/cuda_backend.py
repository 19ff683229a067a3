"""CUDA backend: one thread per sample runs the whole horizon (noise, model, grid GP, costs) in one launch.

Every equation is the CPU kernel's own (`cpu_backend.rollout_kernel`): the device functions here are
compiled from the CPU functions' Python (`gpmppi.gp.cuda_kernels.device_version`), it takes the same five bundles (their
`.args()` tuples), and the same
counter-based noise is drawn, so both backends agree to rounding. The exact GP runs on the CPU
backend only (`Planner` refuses `backend="cuda"` with `gp_mode="exact"`).

Tested under the CUDA simulator (`NUMBA_ENABLE_CUDASIM=1`) against the CPU backend, and compiled to
PTX for a real GPU by `tests/test_cuda_compiles.py` (the simulator runs plain Python, which proves
nothing about what numba's CUDA target accepts).
"""

from __future__ import annotations

import math
import time
from dataclasses import fields

import numba
import numpy as np
from numba import cuda

from gpmppi.gp.cuda_kernels import device_version, set_device_version
from gpmppi.mppi import costs as critic
from gpmppi.mppi import dynamics, gp_table, step
from gpmppi.mppi.bundles import N_COST_TERMS
from gpmppi.mppi.critics.registry import build_by_kind, build_states, build_sums
from gpmppi.mppi.dynamics import DYN_GP, GP_EXACT, GP_SIMPLEX

THREADS_PER_BLOCK = 128


_interp4 = device_version(gp_table.interp4)
_interp4_simplex = device_version(gp_table.interp4_simplex)
_collapse_rows = device_version(gp_table.collapse_rows)


@cuda.jit(device=True, inline=True)
def _grid_residual(gp, scratch, v_ref, w_ref, v, w):  # noqa: ANN001, ANN202 - a CUDA device function
    """The device twin of `dynamics.gp_residual`: the grid table's lookup alone. The CUDA backend runs no exact GP
    (`Planner` refuses it) and the device collapses its table whole (`DeviceInputs.collapsed_table`), so neither the
    exact GP nor the lazy slabs (host atomics) is compiled for it."""
    gp_mode = gp[0]
    if gp_mode == GP_SIMPLEX:
        return _interp4_simplex(gp[1], gp[2], gp[3], gp[4], v, w, v_ref, w_ref)
    return _interp4(gp[1], gp[2], gp[3], gp[4], v, w, v_ref, w_ref)


set_device_version(dynamics.gp_residual, _grid_residual)
_sample_step = device_version(step.sample_step)
_step_inputs = device_version(step.step_inputs)
_fill_velocity_coefficients = device_version(dynamics.fill_velocity_coefficients)
# the critics' sums and state chains from the terms' device twins (the CPU ones are closures, which `device_version`
# cannot rebuild), each made the twin of the CPU function it stands for
_device_jit = cuda.jit(device=True, inline=True)
_device_sums = build_sums(_device_jit, device_version)
for _kind, _sums in _device_sums.items():
    for _field in fields(_sums):
        set_device_version(getattr(critic.SUMS[_kind], _field.name), getattr(_sums, _field.name))
_by_kind = build_by_kind(_device_sums, _device_jit)
for _field in fields(_by_kind):
    if callable(getattr(_by_kind, _field.name)):  # (not the plain flags)
        set_device_version(getattr(critic.BY_KIND, _field.name), getattr(_by_kind, _field.name))
_states = build_states(_device_jit, device_version)
for _field in fields(_states):
    set_device_version(getattr(critic.STATES, _field.name), getattr(_states, _field.name))
_start_state = device_version(critic.start_state)
_advance_state = device_version(critic.advance_state)
_stage_cost = device_version(critic.stage_cost)
_terminal_cost = device_version(critic.terminal_cost)
_fill_weight_vector = device_version(critic.fill_weight_vector)


@cuda.jit(cache=True)
def _rollout_kernel(model, task, sampling, cost, out):
    s = cuda.grid(1)
    eps_out = out.eps_out
    cost_out = out.cost_out
    xy_out = out.xy_out
    samples = eps_out.shape[0]
    if s >= samples:
        return
    tightened_hw = task.tightened_hw
    radii = task.radii
    x0 = sampling.x0
    nominal = sampling.nominal
    dt = sampling.dt
    seed = sampling.seed
    cost_w = cuda.local.array(N_COST_TERMS, numba.float64)
    _fill_weight_vector(cost, cost_w)
    # `dynamics.velocity_coefficients` in a thread's own memory (a device function cannot make an array)
    coef = cuda.local.array(8, numba.float64)
    _fill_velocity_coefficients(model.theta, model.lateral, coef)
    inputs = _step_inputs(model, sampling, sampling.noise_std, sampling.noise_memory, coef)
    horizon = nominal.shape[0]
    n_xy = xy_out.shape[0]
    st = (x0[0], x0[1], x0[2], x0[3], x0[4])
    if s < n_xy:
        xy_out[s, 0, 0] = st[0]
        xy_out[s, 0, 1] = st[1]
    total = 0.0
    state = _start_state(cost_w)  # the stateful critics' values (`costs.start_state`)
    base = (sampling.iteration * samples + s) * horizon
    d = (0.0, 0.0)  # the unit noise of the last step (`rng.sampled_command`)
    for k in range(horizon):
        # the step every backend takes (`step.sample_step`); the exact GP's work arrays: none on the device
        u, d, st, variances = _sample_step(seed, base + k, k, inputs, (), dt, st, d)
        eps_out[s, k, 0] = u[0] - nominal[k, 0]
        eps_out[s, k, 1] = u[1] - nominal[k, 1]
        if s < n_xy:
            xy_out[s, k + 1, 0] = st[0]
            xy_out[s, k + 1, 1] = st[1]
        total += _stage_cost(cost_w, task, tightened_hw[k + 1], radii[k + 1], state, st, u, variances)
        state = _advance_state(state, cost_w)
    total += _terminal_cost(cost_w, task, tightened_hw[horizon], radii[horizon], state, st)
    if math.isnan(total) or math.isinf(total):
        total = math.inf
    cost_out[s] = total


@cuda.jit(cache=True)
def _collapse_kernel(src, collapse_w, out):
    """One row of the collapsed table per thread (`gp_table.collapse_rows`: the same sum in the same order; NVVM fuses
    its multiply-adds, so a value may differ from the host's collapse in the float32 table's last bit)."""
    i = cuda.grid(1)
    if i < src.shape[0]:
        _collapse_rows(src, collapse_w, out, i, i + 1)


# what stands in the kernel's model tuple for the host's lazily collapsed table and its marks: the device collapses
# its own table whole (`DeviceInputs.collapsed_table`)
_NO_LAZY = np.zeros(1, dtype=np.int64)
_NO_TABLE = np.zeros((1, 4), dtype=np.float32)

# arrays up to this size are compared by content to their device copy's source; larger ones by identity
_COMPARE_BYTES = 4096


class DeviceInputs:
    """The device copies of the kernel's inputs, kept between plans: an array is uploaded again only when it changed.

    After MPPI-Generic, which copies each component's parameters to the GPU once: the model (its GP table above
    all, tens of MB) and the task's lookup grids stay on the device, and a plan uploads only what is new (the
    start state, the nominal sequence, the tightened bounds). A small array (up to `_COMPARE_BYTES`) counts as
    unchanged when its content is; a large one when it is the same host array. So a large array the host rewrites
    in place must never come here: the host's lazily collapsed table and its slab marks are the two, and
    `cuda_rollouts` puts placeholders in their place (the device collapses its own table, `collapsed_table`).
    `uploads` counts the uploads per bundle ('model', 'task', 'sampling'), for the tests and benchmarks.
    """

    def __init__(self, timed: bool = False) -> None:
        self._copies: dict[tuple[str, str], tuple[np.ndarray, object]] = {}
        self._outputs: dict[tuple, object] = {}
        self.uploads: dict[str, int] = {"model": 0, "task": 0, "sampling": 0}
        self.collapses = 0  # the tables collapsed on the device (`collapsed_table`)
        self._versions: dict[tuple[str, str], int] = {}  # uploads per (bundle, field): what a device copy holds
        # (the rows' and weights' versions it was collapsed from, the device's collapsed table)
        self._collapsed: tuple[tuple[int, int], object] | None = None
        # with `timed`, each call's phases in ms between CUDA events on the GPU's timeline (host work between two
        # events counts too: the uploads' comparisons, the launch's argument handling), and the host's own time
        # for the bundles and for the launch call (a benchmark's split; it synchronises once more per plan)
        self.timed = timed
        self.phase_ms: dict[str, list[float]] = {"upload": [], "collapse": [], "kernel": [], "download": [],
                                                 "host_bundles": [], "host_launch": []}

    def bundle(self, name: str, args: tuple) -> tuple:
        """A bundle's named tuple (`.args()`) with its arrays replaced by their device copies (scalars as they are)."""
        return type(args)(*(self._array(name, f, a) if isinstance(a, np.ndarray) else a
                            for f, a in zip(args._fields, args, strict=True)))

    def _array(self, name: str, field: str, host: np.ndarray) -> object:
        key = (name, field)
        kept = self._copies.get(key)
        if kept is not None:
            source, device = kept
            small = host.nbytes <= _COMPARE_BYTES
            if source is host or (small and source.shape == host.shape and source.dtype == host.dtype
                                  and np.array_equal(source, host)):
                return device
            if device.shape == host.shape and device.dtype == host.dtype:
                # into the copy already there: a new device array per plan would cost an allocation each time
                device.copy_to_device(host)
            else:
                device = cuda.to_device(host)
        else:
            device = cuda.to_device(host)
        # keep a large array itself (its identity is the test, and holding it keeps its id from being reused), a
        # copy of a small one (its content is the test, even if the caller reuses the array)
        self._copies[key] = (host if host.nbytes > _COMPARE_BYTES else host.copy(), device)
        self.uploads[name] += 1
        self._versions[key] = self._versions.get(key, 0) + 1
        return device

    def collapsed_table(self, src: np.ndarray, collapse_w: np.ndarray) -> object:
        """The device's table collapsed from the per-terrain rows `src` with `collapse_w` (`gp_table.collapse_weights`):
        `src` uploaded once, the collapse run again only when the weights' bytes change."""
        d_src = self._array("model", "table_src", src)
        d_w = self._array("model", "collapse_w", collapse_w)
        held = (self._versions[("model", "table_src")], self._versions[("model", "collapse_w")])
        if self._collapsed is not None and self._collapsed[0] == held:
            return self._collapsed[1]
        table = self._collapsed[1] if self._collapsed is not None else None
        if table is None or table.shape[0] != src.shape[0]:
            table = cuda.device_array((src.shape[0], 4), dtype=np.float32)
        blocks = (src.shape[0] + THREADS_PER_BLOCK - 1) // THREADS_PER_BLOCK
        _collapse_kernel[blocks, THREADS_PER_BLOCK](d_src, d_w, table)
        self._collapsed = (held, table)
        self.collapses += 1
        return table

    def output(self, shape: tuple, dtype: np.dtype) -> object:
        """A device array for an output of this shape, allocated once."""
        key = (tuple(shape), np.dtype(dtype).str)
        found = self._outputs.get(key)
        if found is None:
            found = self._outputs[key] = cuda.device_array(shape, dtype=dtype)
        return found


def cuda_rollouts(
    model: tuple, task: tuple, sampling: tuple, cost: tuple, out: tuple, device: DeviceInputs | None = None,
) -> None:
    """Run the kernel on the bundles' tuples (`.args()`, as the CPU kernel takes them); fill out's arrays.

    `device` keeps the inputs on the device between calls (a planner holds one); None uploads everything."""
    if model.dyn_mode == DYN_GP and model.gp_mode == GP_EXACT:
        raise ValueError("the CUDA backend evaluates the GP by grid only; use gp_mode='grid' or backend='cpu'")
    per_terrain = model.table_src.shape[0] > 1  # the host collapses lazily: the device collapses its own
    if not per_terrain and model.lazy[0] != 0:
        raise ValueError("the model's GP table is marked lazily collapsed but carries no per-terrain rows "
                         "(table_src) to collapse it from")
    device = device if device is not None else DeviceInputs()
    events = [cuda.event() for _ in range(5)] if device.timed else None
    if events:
        events[0].record()
    eps, costs, xy = out.eps_out, out.cost_out, out.xy_out
    d_out = out._replace(eps_out=device.output(eps.shape, eps.dtype), cost_out=device.output(costs.shape, costs.dtype),
                         xy_out=device.output(xy.shape if xy.size else (0, eps.shape[1] + 1, 2), xy.dtype))
    t0 = time.perf_counter()
    d_model = device.bundle("model", model._replace(lazy=_NO_LAZY, table=_NO_TABLE) if per_terrain else model)
    d_task, d_sampling = device.bundle("task", task), device.bundle("sampling", sampling)
    t1 = time.perf_counter()
    if events:
        events[1].record()
    if per_terrain:
        table = device.collapsed_table(model.table_src, model.collapse_w)
        d_model = d_model._replace(table=table)
    if events:
        events[2].record()
    blocks = (eps.shape[0] + THREADS_PER_BLOCK - 1) // THREADS_PER_BLOCK
    # (under the simulator numpy runs the uint64 hash and warns about its intended wrap-around)
    t2 = time.perf_counter()
    _rollout_kernel[blocks, THREADS_PER_BLOCK](d_model, d_task, d_sampling, cost, d_out)
    t3 = time.perf_counter()
    if events:
        events[3].record()
    d_out.eps_out.copy_to_host(eps)
    d_out.cost_out.copy_to_host(costs)
    if xy.size:
        d_out.xy_out.copy_to_host(xy)
    if events:
        events[4].record()
        events[4].synchronize()
        for name, a, b in (("upload", 0, 1), ("collapse", 1, 2), ("kernel", 2, 3), ("download", 3, 4)):
            device.phase_ms[name].append(events[a].elapsed_time(events[b]))
        device.phase_ms["host_bundles"].append((t1 - t0) * 1e3)
        device.phase_ms["host_launch"].append((t3 - t2) * 1e3)
