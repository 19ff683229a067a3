"""The CPU kernel's phases that compute a group's values in loops of their own (vector code) give each sample the bits
of the per-sample functions they stand for: the state step (`dynamics.advance`, every model), the lane critics'
cost (`costs.stage_cost`, whose lane query the phase splits into the grid part and the exact distances) and the GP
table rows' weighted sum (`gp_table.interp4_simplex`'s, read a row at a time by `kernel_flags.row_axpy`).

The costs are compared with the phase as it was (`_add_costs_per_sample`), compiled with the same flags: a
`stage_cost` called on its own rounds a division differently (`arcp` lets LLVM multiply by a reciprocal it hoists
out of a loop), so only the same loop is the reference."""

from __future__ import annotations

import numpy as np

from gpmppi.kernel_flags import phase
from gpmppi.mppi.bundles import N_COST_TERMS, TaskBundle
from gpmppi.mppi.costs import advance_state, stage_cost, start_state
from gpmppi.mppi.cpu_backend import GROUP, _add_costs, _advance_group, _read_rows
from gpmppi.mppi.dynamics import DYN_EDD5, DYN_GP, DYN_UNICYCLE, advance
from gpmppi.mppi.gp_table import interp4_simplex, simplex_nodes
from gpmppi.mppi.lane import build_lane_lookup
from gpmppi.scenarios import circle_lane


@phase
def _add_costs_per_sample(
    n_in: int, st: np.ndarray, cmd: np.ndarray, res: np.ndarray, total: np.ndarray, cost_w: np.ndarray, task: tuple,
    bounds: tuple, state: tuple,
) -> None:
    """`cpu_backend._add_costs` before its lane queries had loops of their own."""
    tightened_hw, radii = bounds
    for j in range(n_in):
        total[j] += stage_cost(cost_w, task, tightened_hw, radii, state,
                               (st[0, j], st[1, j], st[2, j], st[3, j], st[4, j]), (cmd[0, j], cmd[1, j]),
                               (res[2, j], res[3, j]))


def _bits(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype=np.float64).tobytes()


def test_advance_group_gives_each_sample_the_bits_of_advance() -> None:
    rng = np.random.default_rng(0)
    coef = rng.uniform(0.1, 2.0, 8)
    edd5 = np.array([0.9, 0.8, 0.3, -0.4, 0.5, 0.1])
    dt = 0.1
    for mode in (DYN_GP, DYN_EDD5, DYN_UNICYCLE):
        st0 = rng.normal(size=(5, GROUP))
        st0[2] *= 30.0  # headings of many turns
        cmd = rng.normal(size=(2, GROUP))
        res = rng.normal(scale=0.05, size=(4, GROUP))
        for first, n_in in ((0, GROUP), (GROUP, 37), (3 * GROUP, GROUP)):
            xy = np.full((GROUP + 20, 6, 2), -7.0)  # the first GROUP + 20 samples keep their XY
            st = st0.copy()
            _advance_group((mode, coef, edd5), dt, n_in, first, 2, st, cmd, res, xy)
            want_xy = np.full_like(xy, -7.0)
            for j in range(n_in):
                s = advance(mode, dt, coef, edd5, tuple(st0[:, j]), (cmd[0, j], cmd[1, j]), res[0, j], res[1, j])
                assert _bits(st[:, j]) == _bits(np.array(s)), (mode, first, j)
                if first + j < xy.shape[0]:
                    want_xy[first + j, 3] = s[:2]
            assert _bits(st[:, n_in:]) == _bits(st0[:, n_in:])  # samples past the group's end untouched
            assert _bits(xy) == _bits(want_xy), (mode, first)


def test_lane_costs_give_each_sample_the_bits_of_stage_cost() -> None:
    sc = circle_lane()
    lane = build_lane_lookup(sc.task.centerline, True, 2.0)
    tightened = 1.2
    task = TaskBundle.for_lane(lane, sc.task.half_width, np.full(41, tightened), 1.75).args()
    rng = np.random.default_rng(1)
    cost_w = rng.uniform(0.5, 3.0, N_COST_TERMS)
    state = advance_state(start_state(cost_w), cost_w)
    cell = 1.0 / lane.inv_cell
    checked_exact = 0
    for trial in range(6):
        ang = rng.uniform(0.0, 2.0 * np.pi, GROUP)
        # around the lane, at the tightened edge to within a cell (exact distances), and far outside the grid
        off = rng.choice([rng.normal(0.0, 1.0), tightened + rng.uniform(-cell, cell), 15.0], GROUP)
        rad = 8.25 + off * rng.choice([-1.0, 1.0], GROUP)
        st = np.empty((5, GROUP))
        st[0] = rad * np.cos(ang)
        st[1] = rad * np.sin(ang)
        st[2] = ang + rng.normal(0.0, 0.3, GROUP)
        st[3] = rng.uniform(0.0, 2.0, GROUP)
        st[4] = rng.normal(0.0, 0.5, GROUP)
        cmd = rng.normal(size=(2, GROUP))
        res = np.abs(rng.normal(scale=0.01, size=(4, GROUP)))
        n_in = GROUP if trial % 2 == 0 else 29
        total = rng.normal(size=GROUP)
        want = total.copy()
        lane_buf = np.empty((4, GROUP))
        _add_costs(n_in, st, cmd, res, total, cost_w, task, (tightened, np.zeros(0)), state, lane_buf)
        _add_costs_per_sample(n_in, st, cmd, res, want, cost_w, task, (tightened, np.zeros(0)), state)
        assert _bits(total) == _bits(want), trial
        checked_exact += int(np.sum(lane_buf[3, :n_in] != 0.0))
    assert checked_exact > 20  # the exact-distance path ran (near the threshold and outside the grid)


def test_read_rows_gives_each_sample_the_bits_of_the_simplex_sum() -> None:
    """Each sample's five rows weighed and summed in float32 in vertex order, one rounding per multiply and per add,
    as numpy's float32 scalars do and as `interp4_simplex` does at the same point (its table and grid)."""
    rng = np.random.default_rng(3)
    dims = np.array([5, 6, 4, 7], dtype=np.int64)
    lo = np.array([0.0, -1.0, 0.0, -2.0])
    inv_step = np.array([2.0, 2.5, 1.5, 1.75])
    table = rng.normal(size=(int(np.prod(dims)), 4)).astype(np.float32)
    table[:, 2:] = np.abs(table[:, 2:]) * np.float32(1e-3)  # variances: small and positive, as the model's
    points = rng.uniform(lo - 0.2, lo + (dims - 1) / inv_step + 0.2, size=(GROUP, 4))  # some outside: clamped
    nodes = np.zeros((5, GROUP), dtype=np.uint64)
    node_w = np.zeros((5, GROUP), dtype=np.float32)
    for j in range(GROUP):
        n0, n1, n2, n3, n4, w0, w1, w2, w3, w4 = simplex_nodes(dims, lo, inv_step, *points[j])
        nodes[:, j] = (n0, n1, n2, n3, n4)
        node_w[:, j] = (w0, w1, w2, w3, w4)
    for n_in in (GROUP, 37):
        res = np.full((4, GROUP), -5.0)
        _read_rows(n_in, table.reshape(-1), nodes, node_w, res)
        for j in range(n_in):
            want = node_w[0, j] * table[nodes[0, j]]
            for q in range(1, 5):
                want = want + node_w[q, j] * table[nodes[q, j]]
            assert want.dtype == np.float32
            assert _bits(res[:, j]) == _bits(want), (n_in, j)
            assert _bits(res[:, j]) == _bits(np.array(interp4_simplex(table, dims, lo, inv_step, *points[j]))), j
        assert np.all(res[:, n_in:] == -5.0)  # samples past the group's end untouched
