"""The GP table collapsed lazily for moving terrain weights (`lazy_collapse`): plans identical to the bit to those with
the table collapsed whole, slabs that match the whole collapse, the ready box and the read marks, and a collapse that
matches its formula."""

from __future__ import annotations

import numpy as np
import pytest
from cached_models import shipped_model
from numba import njit

from gpmppi.models.kinematic_unicycle import kinematic_step
from gpmppi.mppi.config import PlannerConfig
from gpmppi.mppi.gp_table import collapse_into, collapse_table, collapse_weights, rollout_order, terrain_rows
from gpmppi.mppi.lazy_collapse import (
    box_hull,
    cell_stamps,
    empty_box,
    ensure_block,
    in_ready_box,
    lazy_state,
    note_read,
    read_box,
    ready_box,
    slab_versions,
)
from gpmppi.mppi.planner import Planner
from gpmppi.scenarios import circle_lane


@pytest.fixture(scope="module")
def model():
    return shipped_model()


def _closed_loop(model, steps: int = 12, prepare: bool = False, **config) -> tuple[Planner, np.ndarray]:
    """A few plans on the circle lane with weights that move every plan (a seeded walk), as the terrain service's."""
    planner = Planner(PlannerConfig(backend="cpu", samples=256, horizon=20, seed=5, **config), model)
    sc = circle_lane()
    x = sc.start.copy()
    rng = np.random.default_rng(1)
    w = np.array([0.5, 0.3, 0.2])
    out = []
    for k in range(steps):
        if k % 4 != 3:  # every fourth plan keeps the weights (the table is then collapsed whole, once)
            w = np.clip(w + rng.normal(0.0, 0.05, 3), 0.01, 1.0)
            w = w / w.sum()
        if prepare:  # as the planner service does when new weights arrive
            planner.prepare(w)
        r = planner.plan(x, sc.task, w)
        out.append(np.concatenate([r.controls.ravel(), r.states.ravel(), r.covariances.ravel(), r.sample_costs,
                                   [r.cost]]))
        x = kinematic_step(x, r.control, 0.1)
    return planner, np.array(out)


@pytest.mark.parametrize(("interpolation", "prepare"), [("simplex", False), ("simplex", True),
                                                        ("multilinear", False)])
def test_lazy_plans_are_identical_to_plans_with_the_table_collapsed_whole(
    model, interpolation: str, prepare: bool,
) -> None:
    lazy, plans_lazy = _closed_loop(model, prepare=prepare, grid_interpolation=interpolation)
    whole, plans_whole = _closed_loop(model, grid_interpolation=interpolation, table_collapse="whole")
    # one collapsed lazily (a new version per weights), the other whole
    assert lazy.terrain.lazy_collapse and lazy.terrain.version > 5 and not whole.terrain.lazy_collapse
    np.testing.assert_array_equal(plans_lazy, plans_whole)


def test_the_slabs_a_plan_made_current_equal_the_whole_collapse_and_the_rest_were_not_touched(model) -> None:
    planner, _ = _closed_loop(model, steps=3)
    grid = planner.terrain.grid
    lazy, dims = grid["lazy"], grid["dims"]
    current = np.flatnonzero(slab_versions(lazy) == lazy[0])
    # the rollouts reach a small part of the table: that is the saving
    assert 0 < current.size < 0.5 * slab_versions(lazy).size
    whole = np.empty_like(grid["table"])
    collapse_into(grid["table_src"], grid["collapse_w"], whole)
    rows = (current[:, None] * dims[3] + np.arange(dims[3])[None, :]).ravel()
    np.testing.assert_array_equal(grid["table"][rows], whole[rows])


def test_the_collapse_is_the_weighted_sum_of_the_terrains(model) -> None:
    """Against the formula in numpy: means weighted by w, latent variances by w^2, plus the likelihood noise."""
    table = model.grid().table
    m = len(model.terrains)
    w = np.array([0.6, 0.1, 0.3])
    noise = (2e-4, 3e-3)
    got = collapse_table(np.ascontiguousarray(table, dtype=np.float32), w, noise)
    # the reference sums the same float32 inputs in float64; the result is rounded to float32 once
    ordered = np.transpose(table.astype(np.float32), (2, 3, 0, 1, 4)).astype(np.float64)
    mean = ordered[..., : 2 * m].reshape(*ordered.shape[:4], m, 2)
    var = ordered[..., 2 * m :].reshape(*ordered.shape[:4], m, 2)
    want = np.concatenate([np.einsum("...tc,t->...c", mean, w), np.einsum("...tc,t->...c", var, w * w) + noise], -1)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-12)


def test_terrain_rows_put_each_terrains_four_values_side_by_side(model) -> None:
    ordered = rollout_order(model.grid().table)
    rows = terrain_rows(ordered)
    m = len(model.terrains)
    flat = ordered.reshape(-1, 4 * m)
    for t in range(m):
        np.testing.assert_array_equal(rows[:, 4 * t : 4 * t + 2], flat[:, 2 * t : 2 * t + 2])
        np.testing.assert_array_equal(rows[:, 4 * t + 2 : 4 * t + 4], flat[:, 2 * m + 2 * t : 2 * m + 2 * t + 2])
    np.testing.assert_array_equal(collapse_weights([0.5, 0.25, 0.25], (1.0, 2.0)),
                                  [0, 0, 1, 2, 0.5, 0.5, 0.25, 0.25, 0.25, 0.25, 0.0625, 0.0625, 0.25, 0.25,
                                   0.0625, 0.0625])


def test_weights_held_for_a_second_plan_collapse_the_whole_table_once(model) -> None:
    planner = Planner(PlannerConfig(backend="cpu", samples=128, horizon=10), model)
    sc = circle_lane()
    w = np.array([0.2, 0.3, 0.5])
    planner.prepare(w)
    planner.prepare(w)  # no plan ran with them yet: still lazy
    lazy = planner.terrain.grid["lazy"]
    assert lazy[0] != 0
    planner.plan(sc.start, sc.task, w)
    assert lazy[0] != 0
    planner.plan(sc.start, sc.task, w)
    assert lazy[0] == 0  # the checks are off
    whole = np.empty_like(planner.terrain.grid["table"])
    collapse_into(planner.terrain.grid["table_src"], planner.terrain.grid["collapse_w"], whole)
    np.testing.assert_array_equal(planner.terrain.grid["table"], whole)
    planner.plan(sc.start, sc.task, np.array([0.3, 0.3, 0.4]))
    assert lazy[0] >= np.max(slab_versions(lazy)) and lazy[0] != 0  # a new version: no slab holds a later one


def _slabs_of_cells(cells: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """The slabs the cells `cells` (a mask over the cell stamps) read: each cell's eight, one up each outer axis."""
    shape = tuple(int(d) for d in dims[:3])
    m = cells.reshape(shape)
    out = m.copy()
    for d0 in (0, 1):
        for d1 in (0, 1):
            for d2 in (0, 1):
                out[d0:, d1:, d2:] |= m[: shape[0] - d0, : shape[1] - d1, : shape[2] - d2]
    return out.ravel()


def _current_rows_match_the_whole_collapse(planner: Planner, slabs: np.ndarray) -> None:
    grid = planner.terrain.grid
    whole = np.empty_like(grid["table"])
    collapse_into(grid["table_src"], grid["collapse_w"], whole)
    dim3 = grid["dims"][3]
    rows = (np.flatnonzero(slabs)[:, None] * dim3 + np.arange(dim3)).ravel()
    np.testing.assert_array_equal(grid["table"][rows], whole[rows])


def _box_cells(box: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """A mask over the cells of the three outer axes: those of the box (lo0, hi0, lo1, hi1, lo2, hi2)."""
    mask = np.zeros(tuple(int(d) for d in dims[:3]), dtype=bool)
    mask[box[0] : box[1] + 1, box[2] : box[3] + 1, box[4] : box[5] + 1] = True
    return mask.ravel()


def _bounding_box(cells: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """The smallest box (lo0, hi0, lo1, hi1, lo2, hi2) holding the cells of the mask `cells`."""
    idx = np.array(np.unravel_index(np.flatnonzero(cells), tuple(int(d) for d in dims[:3])))
    return np.column_stack([idx.min(axis=1), idx.max(axis=1)]).ravel()


def _all_eight_current(slabs_current: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """A mask over the cells: those (each index within 0 .. dims - 2) whose eight slabs are all current."""
    shape = tuple(int(d) for d in dims[:3])
    c = slabs_current.reshape(shape)
    out = np.zeros(shape, dtype=bool)
    inner = c[:-1, :-1, :-1].copy()
    for d0 in (0, 1):
        for d1 in (0, 1):
            for d2 in (0, 1):
                inner &= c[d0 : shape[0] - 1 + d0, d1 : shape[1] - 1 + d1, d2 : shape[2] - 1 + d2]
    out[:-1, :-1, :-1] = inner
    return out.ravel()


def test_new_weights_make_every_slab_stale_and_prepare_collapses_those_the_last_plan_read(model) -> None:
    planner = Planner(PlannerConfig(backend="cpu", samples=128, horizon=10), model)
    planner.terrain.read_history = 1  # the last plan's reads alone (the history: the next test)
    sc = circle_lane()
    planner.plan(sc.start, sc.task, np.array([0.2, 0.3, 0.5]))
    lazy, dims = planner.terrain.grid["lazy"], planner.terrain.grid["dims"]
    slabs, cells = slab_versions(lazy), cell_stamps(lazy)
    assert slabs.size == cells.size == (lazy.size - 13) // 2
    before = lazy[0]
    planner.terrain.set_weights(np.array([0.25, 0.3, 0.45]))  # as `plan` does: nothing collapsed yet
    assert lazy[0] == before + 1 and not np.any(slabs == lazy[0]) and not np.any(np.abs(cells) == lazy[0])
    np.testing.assert_array_equal(ready_box(lazy), empty_box())
    np.testing.assert_array_equal(read_box(lazy), empty_box())
    planner.plan(sc.start, sc.task, np.array([0.25, 0.3, 0.45]))
    # no ready box (no `prepare`): every lookup went through its cell's stamp
    read_cells = cells == lazy[0]
    read = _slabs_of_cells(read_cells, dims)
    # the plan's lookups made current exactly the slabs of the cells they read, and the read box holds them all
    np.testing.assert_array_equal(slabs == lazy[0], read)
    np.testing.assert_array_equal(read_box(lazy), _bounding_box(read_cells, dims))
    box = read_box(lazy).copy()
    before = lazy[0]
    planner.prepare(np.array([0.3, 0.3, 0.4]))  # as the planner service does when new weights arrive
    assert lazy[0] == before + 1
    # current: the slabs of the cells the last plan read and of every cell of their box, which is the ready box now;
    # every cell whose eight slabs that made current is stamped current, not read yet
    want = _slabs_of_cells(read_cells | _box_cells(box, dims), dims)
    assert want.sum() > read.sum()
    np.testing.assert_array_equal(slabs == lazy[0], want)
    np.testing.assert_array_equal(ready_box(lazy), box)
    np.testing.assert_array_equal(read_box(lazy), empty_box())
    np.testing.assert_array_equal(cells == -lazy[0], _all_eight_current(slabs == lazy[0], dims))
    assert not np.any(cells == lazy[0])
    _current_rows_match_the_whole_collapse(planner, want)
    planner.prepare(np.array([0.3, 0.3, 0.4]))  # the same weights: nothing to do
    assert lazy[0] == before + 1
    # the next plan's lookups inside the ready box check nothing and stamp nothing; those outside it stamp their cells
    # read (collapsing their slabs where stale); the read box holds both
    x = kinematic_step(sc.start, np.array([1.0, 0.8]), 0.5)
    planner.plan(x, sc.task, np.array([0.3, 0.3, 0.4]))
    stamped = cells == lazy[0]
    assert stamped.any() and not np.any(stamped & _box_cells(box, dims))
    box2 = read_box(lazy).copy()
    assert not np.array_equal(box2, box)
    assert np.all(_box_cells(box2, dims)[stamped])
    planner.prepare(np.array([0.35, 0.3, 0.35]))
    want = _slabs_of_cells(stamped | _box_cells(box2, dims), dims)
    np.testing.assert_array_equal(slabs == lazy[0], want)
    np.testing.assert_array_equal(ready_box(lazy), box2)
    _current_rows_match_the_whole_collapse(planner, want)
    state = lazy_state(np.array([2, 3, 4, 5]))
    assert state[0] == 1 and state.size == 13 + 2 * 2 * 3 * 4 and not state[13:].any()
    np.testing.assert_array_equal(ready_box(state), empty_box())


@pytest.mark.parametrize("ready_history", [3, 1])
def test_prepare_collapses_the_slabs_read_by_the_plans_of_the_last_versions(model, ready_history: int) -> None:
    """`read_history` = 3: after each `prepare`, the slabs current are those of the hull of the read boxes of the plans
    of the last `ready_history` versions (the ready box) and of the cells the plans of the last three versions stamped
    read, with their whole-collapse values."""
    planner = Planner(PlannerConfig(backend="cpu", samples=128, horizon=10, seed=2), model)
    planner.terrain.read_history = 3
    planner.terrain.ready_history = ready_history
    lazy, dims = planner.terrain.grid["lazy"], planner.terrain.grid["dims"]
    sc = circle_lane()
    x = sc.start.copy()
    rng = np.random.default_rng(4)
    w = np.array([0.5, 0.3, 0.2])
    stamped, boxes = [], []
    for _ in range(7):
        w = np.clip(w + rng.normal(0.0, 0.05, 3), 0.01, 1.0)
        w = w / w.sum()
        planner.prepare(w)
        if boxes:
            hull = box_hull(boxes[-ready_history:])
            np.testing.assert_array_equal(ready_box(lazy), hull)
            want = _slabs_of_cells(np.any(stamped[-3:], axis=0) | _box_cells(hull, dims), dims)
            np.testing.assert_array_equal(slab_versions(lazy) == lazy[0], want)
            _current_rows_match_the_whole_collapse(planner, want)
        r = planner.plan(x, sc.task, w)
        stamped.append(cell_stamps(lazy) == lazy[0])
        boxes.append(read_box(lazy).copy())
        x = kinematic_step(x, r.control, 0.1)
    # the hull of three boxes grew past the last plan's box: the history is used
    assert _box_cells(box_hull(boxes[-3:]), dims).sum() > _box_cells(boxes[-1], dims).sum()
    if ready_history == 1:  # with a ready box (plans 2-7), some lookups outside it went through their stamps
        assert any(s.any() for s in stamped[1:])


def test_box_hull_and_the_atomic_extremes() -> None:
    a = np.array([2, 5, 0, 3, 7, 9])
    b = np.array([1, 4, 2, 6, 8, 8])
    np.testing.assert_array_equal(box_hull([a, empty_box(), b]), [1, 5, 0, 6, 7, 9])
    np.testing.assert_array_equal(box_hull([]), empty_box())
    lazy = lazy_state(np.array([3, 3, 3, 4]))
    note_read_box(lazy, 1, 1, 0, 1, 0, 0)
    note_read_box(lazy, 0, 1, 1, 1, 1, 1)
    np.testing.assert_array_equal(read_box(lazy), [0, 1, 0, 1, 0, 1])
    assert in_box(lazy, 0, 0, 0) is False  # the ready box is empty
    ready_box(lazy)[:] = [0, 1, 0, 0, 1, 1]
    assert in_box(lazy, 1, 0, 1) and not in_box(lazy, 1, 1, 1) and not in_box(lazy, 1, 0, 0)


@njit
def note_read_box(lazy: np.ndarray, lo0: int, hi0: int, lo1: int, hi1: int, lo2: int, hi2: int) -> None:
    note_read(lazy, lo0, hi0, lo1, hi1, lo2, hi2)


@njit
def in_box(lazy: np.ndarray, i0: int, i1: int, i2: int) -> bool:
    return in_ready_box(lazy, i0, i1, i2)


def test_a_lookup_outside_the_cells_writes_nothing(model) -> None:
    """A NaN state reaches `ensure_block` through the multilinear cell lookup as a garbage index: nothing is written."""
    planner = Planner(PlannerConfig(backend="cpu", samples=64, horizon=5), model)
    planner.prepare(np.array([0.2, 0.3, 0.5]))
    grid = planner.terrain.grid
    lazy_before, table_before = grid["lazy"].copy(), grid["table"].copy()
    for cell in ((-1, 0, 0), (0, int(grid["dims"][1]) - 1, 0), (np.iinfo(np.int64).min, 0, 0)):
        ensure_block(grid["lazy"], grid["table_src"], grid["collapse_w"], grid["table"], grid["dims"], *cell)
    np.testing.assert_array_equal(grid["lazy"], lazy_before)
    np.testing.assert_array_equal(grid["table"], table_before)
