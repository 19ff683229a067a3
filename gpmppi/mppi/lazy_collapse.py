"""The GP table collapsed lazily for moving terrain weights: slabs collapsed as the readers reach them, the ready box
that `Planner.prepare` collapses ahead, the cells' stamps and the read marks (the comment below says how).

`gp_table` holds the collapse itself (`collapse_rows`: the same bits whoever collapses a row) and the interpolation;
the rollout kernels and the serial readers (`dynamics.gp_residual`) call `ensure_block` / `ensure_block_at` here.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from gpmppi.kernel_flags import fetch_max, fetch_min, load_acquire, prefetch_row, store_release
from gpmppi.mppi.gp_table import collapse_rows

# ------------------------------------------------------------------------------------------- lazy collapse
# New terrain weights arrive every cycle, and collapsing the whole table for them cost about as much as the plan
# itself (it reads every node of every terrain). A plan reads only the nodes near the velocities and commands its
# rollouts reach. So the planner only marks the table stale (`lazy[0]`, the weights' version, goes up)
# and the readers collapse the slabs they are about to read. A slab is the nodes that share the three outer indices
# (v, omega, v_ref in `TABLE_AXES` order): `dims[3]` consecutive rows, slab s holding rows s * dims[3] on, and
# `lazy[LAZY_SLABS + s]` is the version it holds. (Slabs of 8 or 16 rows measured slower: the checks cost more than
# the rows they spared.) A slab is collapsed by the same function as the whole table (`collapse_rows`), so its values
# are the same to the bit whoever collapses it, and a plan is identical to one with the whole table collapsed.
# Two threads may collapse one slab at once: both write the same bytes, and each publishes the slab with a
# release store only after its own writes (`store_release`), which a reader's acquire load (`load_acquire`)
# pairs with.
# The ready box: `Planner.prepare` collapses ahead, for the next weights, every slab of a box of cells (the three
# outer axes' cell indices, `lazy[LAZY_READY:LAZY_READY + 6]` = lo0, hi0, lo1, hi1, lo2, hi2, inclusive): the hull of
# the boxes the plans of the last `TerrainTable.ready_history` versions read (`lazy[LAZY_READ:LAZY_READ + 6]`, each
# lookup's cell folded in; the last version's box alone by default).
# A lookup inside the ready box reads current slabs and checks nothing else: a test of its three indices, which the
# rollouts run in the loop that computes the lookups' simplex corners (vector code), so a step with every lookup
# inside it costs no scalar check at all. (Before, each lookup's cell was checked against the thread's seen marks and
# each cell a thread met first, ~1,900 a plan for each of the two threads, had its stamp checked and stamped read, by
# a call: 0.13-0.21 ms a plan on one thread.)
# Cell stamps, for the lookups outside the ready box: a lookup reads the eight slabs of its cell (`ensure_block`), and
# checking eight slab versions for each cell a thread meets cost more than the stale slabs' collapse. So each cell of
# the three outer axes has a stamp too, `lazy[LAZY_SLABS + n + key]` (n slabs, `block_key`): `version` when its eight
# slabs are current and a lookup read it in this version, `-version` when they were made current ahead
# (`collapse_slabs_at`) and no lookup read it yet; a reader checks the one stamp, and the eight slabs only when it is
# neither. The slabs `Planner.prepare` collapses ahead are those of the ready box to come and of the cells stamped
# `version` by the plans of the last few versions; without the read marks (every slab ever collapsed ahead collapsed
# again) that set grew plan after plan (3,488 slabs read a plan, 7,549 current).
LAZY_READY = 1  # lazy[1:7]: the ready box (cells whose slabs are current for the version in lazy[0])
LAZY_READ = 7  # lazy[7:13]: the box of the cells read in this version
LAZY_SLABS = 13  # lazy[13:13 + n]: the slabs' versions; then the n cells' stamps
_NO_CELL = 2**31 - 1  # an empty box's lower bounds (its upper bounds -1); int32, as the rollouts test boxes


def empty_box() -> np.ndarray:
    """A box of no cells (lo0, hi0, lo1, hi1, lo2, hi2; each lo above each hi)."""
    return np.array([_NO_CELL, -1, _NO_CELL, -1, _NO_CELL, -1], dtype=np.int64)


def box_hull(boxes: list[np.ndarray]) -> np.ndarray:
    """The smallest box holding every box of `boxes` (empty ones add nothing)."""
    hull = empty_box()
    for box in boxes:
        if box[0] <= box[1] and box[2] <= box[3] and box[4] <= box[5]:
            hull[0::2] = np.minimum(hull[0::2], box[0::2])
            hull[1::2] = np.maximum(hull[1::2], box[1::2])
    return hull


@njit(cache=True, inline="always")
def block_key(dims: np.ndarray, i0: int, i1: int, i2: int) -> int:
    """The cell (i0, i1, i2) of the three outer axes as one index below `block_keys` (`ensure_block`'s unit)."""
    return (i0 * dims[1] + i1) * dims[2] + i2


def block_keys(dims: np.ndarray) -> int:
    """The number of cells of the three outer axes (as many as slabs)."""
    return int(dims[0]) * int(dims[1]) * int(dims[2])


@njit(cache=True, inline="always")
def lazy_cells(lazy: np.ndarray) -> int:
    """The number of slabs (and cells) of a lazily collapsed table's `lazy`."""
    return (lazy.shape[0] - LAZY_SLABS) // 2


@njit(cache=True, inline="always")
def in_ready_box(lazy: np.ndarray, i0: int, i1: int, i2: int) -> bool:
    """Whether the cell (i0, i1, i2) lies in the ready box: its eight slabs are current."""
    return (lazy[1] <= i0 <= lazy[2]) and (lazy[3] <= i1 <= lazy[4]) and (lazy[5] <= i2 <= lazy[6])


@njit(cache=True, inline="always")
def ready_box_of(lazy: np.ndarray) -> tuple[np.int32, np.int32, np.int32, np.int32, np.int32, np.int32]:
    """The ready box (lo0, hi0, lo1, hi1, lo2, hi2) as int32, as the rollouts' box test takes it; an empty box for a
    table collapsed whole (`lazy` = [0])."""
    if lazy.shape[0] < LAZY_SLABS:
        return (np.int32(_NO_CELL), np.int32(-1), np.int32(_NO_CELL), np.int32(-1), np.int32(_NO_CELL), np.int32(-1))
    return (np.int32(lazy[1]), np.int32(lazy[2]), np.int32(lazy[3]), np.int32(lazy[4]), np.int32(lazy[5]),
            np.int32(lazy[6]))


@njit(cache=True, inline="always")
def note_read(lazy: np.ndarray, lo0: int, hi0: int, lo1: int, hi1: int, lo2: int, hi2: int) -> None:
    """Fold the box of cells (lo0 .. hi0, lo1 .. hi1, lo2 .. hi2) into this version's read box (atomically: the
    rollout threads each fold in theirs; an update only where the box grows, which is rare after a plan's first)."""
    if lo0 < lazy[7]:
        fetch_min(lazy, 7, lo0)
    if hi0 > lazy[8]:
        fetch_max(lazy, 8, hi0)
    if lo1 < lazy[9]:
        fetch_min(lazy, 9, lo1)
    if hi1 > lazy[10]:
        fetch_max(lazy, 10, hi1)
    if lo2 < lazy[11]:
        fetch_min(lazy, 11, lo2)
    if hi2 > lazy[12]:
        fetch_max(lazy, 12, hi2)


@njit(cache=True, nogil=True, _nrt=False)
def ensure_block(lazy: np.ndarray, src: np.ndarray, collapse_w: np.ndarray, table: np.ndarray, dims: np.ndarray,
                 i0: int, i1: int, i2: int) -> None:
    """Make current the eight slabs an interpolation in the cell (i0, i1, i2) of the three outer axes reads
    (nodes i..i+1 on each axis; each index at most dims - 2, as the cell lookups clamp them), and note the read."""
    if lazy[0] == 0:  # the whole table is collapsed
        return
    if not (0 <= i0 <= dims[0] - 2 and 0 <= i1 <= dims[1] - 2 and 0 <= i2 <= dims[2] - 2):
        return  # not a cell (a NaN state through `grid_cell`): write nothing; the reader's lookup is garbage anyway
    note_read(lazy, i0, i0, i1, i1, i2, i2)
    if in_ready_box(lazy, i0, i1, i2):
        return
    ensure_block_at(lazy, src, collapse_w, table, dims, block_key(dims, i0, i1, i2))


@njit(cache=True, inline="always")
def cell_current(lazy: np.ndarray, first: int) -> bool:
    """Whether the eight slabs of the cell whose `block_key` is `first` are current, by the cell's stamp alone (one
    read); a cell made current ahead (`collapse_slabs_at`) is stamped read (`version`) here."""
    version = lazy[0]
    cell = LAZY_SLABS + lazy_cells(lazy) + first
    held = load_acquire(lazy, cell)
    if held == version:
        return True
    if held == -version:  # made current ahead, now read: mark it read
        store_release(lazy, cell, version)
        return True
    return False


@njit(cache=True, nogil=True, _nrt=False)
def ensure_block_at(lazy: np.ndarray, src: np.ndarray, collapse_w: np.ndarray, table: np.ndarray, dims: np.ndarray,
                    first: int) -> None:
    """`ensure_block` for the cell whose `block_key` is `first` (a cell of the lookups, each index within
    0 .. dims - 2), by its stamp and slabs alone (the caller tested the ready box): its lowest slab is slab `first`,
    the other seven lie one step up each outer axis.

    The cell's stamp first (`cell_current`). Else two passes over its slabs: the first finds the stale slabs and
    requests their rows from memory, the second collapses them, so that the slabs' memory reads overlap instead of
    waiting one after another (they lie far apart); then the cell is stamped read, after its slabs (a reader that
    sees the stamp sees them)."""
    if cell_current(lazy, first):
        return
    version = lazy[0]
    rows = dims[3]
    s1 = dims[2]
    s0 = dims[1] * s1
    stale = 0
    for b in range(8):
        slab = first + (b >> 2) * s0 + ((b >> 1) & 1) * s1 + (b & 1)
        if load_acquire(lazy, LAZY_SLABS + slab) != version:
            stale |= 1 << b
            for r in range(slab * rows, (slab + 1) * rows):
                prefetch_row(src, r)
    for b in range(8):
        if stale & (1 << b):
            slab = first + (b >> 2) * s0 + ((b >> 1) & 1) * s1 + (b & 1)
            collapse_rows(src, collapse_w, table, slab * rows, (slab + 1) * rows)
            store_release(lazy, LAZY_SLABS + slab, version)
    store_release(lazy, LAZY_SLABS + lazy_cells(lazy) + first, version)


@njit(cache=True, parallel=True)
def collapse_slabs_at(lazy: np.ndarray, src: np.ndarray, collapse_w: np.ndarray, table: np.ndarray, dims: np.ndarray,
                      old: int, new: int, threads: int, last_read: np.ndarray, since: int, ready: np.ndarray) -> None:
    """Collapse, for the weights of version `new` (`collapse_w`), every slab of the cells of the box `ready` (lo0, hi0,
    lo1, hi1, lo2, hi2; `empty_box` for none) and every slab read by a plan of version `since` or later through a
    stamped cell, stamp each `new`, and stamp `-new` (current, not read yet) each cell whose eight slabs that made
    current: ahead of the next plan (`Planner.prepare`), on `threads` threads. With no plan running. `last_read` (one
    per slab) holds the last version whose plan read each slab through a stamped cell (a lookup outside the ready
    box); the slabs of the cells stamped `old` are recorded in it first. The caller then sets the ready box.

    The slabs the next plan reads are mostly those the last one read, but about one in ten is new to it (the samples'
    noise is new each plan and the cloud's fringe moves): of those, most were read by one of the few plans before
    (`since` = `new` - 4 left 92 of 3,560 slabs for the plan to collapse, against 320 with the last plan's alone,
    for 18 % more slabs collapsed here; docs/benchmarks.md, "Moving terrain weights").

    The slabs are listed first and dealt out in turn (slab i to thread i mod threads): the slabs a plan reads lie
    together (near the robot's velocities), so a split of the table in halves gave one thread nearly all of them
    and ran no faster than one thread. Each thread requests its next slab's rows while it collapses this one."""
    rows = dims[3]
    n = lazy_cells(lazy)
    s1 = dims[2]
    s0 = dims[1] * s1
    stamps = LAZY_SLABS + n
    for key in range(n):
        if lazy[stamps + key] == old:
            for b in range(8):
                last_read[key + (b >> 2) * s0 + ((b >> 1) & 1) * s1 + (b & 1)] = old
    todo = np.empty(n, dtype=np.int64)
    count = 0
    for s in range(n):
        if last_read[s] >= since:
            todo[count] = s
            count += 1
    # the slabs of the box's cells: indices lo .. hi + 1 on each axis (an empty box has none)
    for i0 in range(ready[0], ready[1] + 2):
        for i1 in range(ready[2], ready[3] + 2):
            for i2 in range(ready[4], ready[5] + 2):
                s = (i0 * dims[1] + i1) * s1 + i2
                if last_read[s] < since:
                    todo[count] = s
                    count += 1
    for t in prange(threads):
        for q in range(t, count, threads):
            if q + threads < count:
                ahead = todo[q + threads]
                for r in range(ahead * rows, (ahead + 1) * rows):
                    prefetch_row(src, r)
            s = todo[q]
            collapse_rows(src, collapse_w, table, s * rows, (s + 1) * rows)
            lazy[LAZY_SLABS + s] = new
    # a cell whose eight slabs are current has its lowest slab among them
    top0 = dims[0] - 2
    top1 = dims[1] - 2
    top2 = dims[2] - 2
    for q in range(count):
        key = todo[q]
        i2 = key % dims[2]
        i1 = (key // dims[2]) % dims[1]
        i0 = key // s0
        if i0 > top0 or i1 > top1 or i2 > top2:
            continue
        current = True
        for b in range(8):
            if lazy[LAZY_SLABS + key + (b >> 2) * s0 + ((b >> 1) & 1) * s1 + (b & 1)] != new:
                current = False
        if current:
            lazy[stamps + key] = -new


def slab_versions(lazy: np.ndarray) -> np.ndarray:
    """The slabs' versions of a lazily collapsed table's `lazy` (a view)."""
    return lazy[LAZY_SLABS : LAZY_SLABS + (lazy.shape[0] - LAZY_SLABS) // 2]


def cell_stamps(lazy: np.ndarray) -> np.ndarray:
    """The cells' stamps of a lazily collapsed table's `lazy` (a view; `ensure_block_at`)."""
    return lazy[LAZY_SLABS + (lazy.shape[0] - LAZY_SLABS) // 2 :]


def ready_box(lazy: np.ndarray) -> np.ndarray:
    """The ready box of a lazily collapsed table's `lazy` (a view: lo0, hi0, lo1, hi1, lo2, hi2)."""
    return lazy[LAZY_READY : LAZY_READY + 6]


def read_box(lazy: np.ndarray) -> np.ndarray:
    """The box of the cells read in the current version (a view: lo0, hi0, lo1, hi1, lo2, hi2)."""
    return lazy[LAZY_READ : LAZY_READ + 6]


def lazy_state(dims: np.ndarray) -> np.ndarray:
    """A lazily collapsed table's versions (`lazy`): [0] the current one (1), the ready box and the read box (empty),
    then each slab's version, then each cell's stamp (`ensure_block_at`), all 0: every slab stale."""
    state = np.zeros(LAZY_SLABS + 2 * block_keys(dims), dtype=np.int64)
    state[0] = 1
    ready_box(state)[:] = empty_box()
    read_box(state)[:] = empty_box()
    return state
