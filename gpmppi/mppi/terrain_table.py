"""The rollouts' model for the current terrain weights: the weights, the GP table collapsed with them, the noise.

`TerrainTable` owns what of the planner depends on the terrain weights:

* the weights themselves (checked onto the simplex, `check_weights`) and the ensemble's likelihood noise
  (`noise_var`: sum_i w_i^2 noise_i);
* the GP's evaluation, set up once: a grid table (simplex or multilinear interpolation) whose per-terrain rows are
  collapsed with the weights, or the exact GP's training data;
* the collapse of the grid table when the weights change: whole at once (`table_collapse="whole"`), or lazily
  (the default): the weights' version moves on, every slab goes stale, and the readers collapse the slabs they
  read (`lazy_collapse.ensure_block`); `set_weights(w, ahead=True)` collapses at once the slabs of the box of cells
  the plans of the last weight version read, and of the cells the last few versions read outside their boxes (the
  service's `prepare`, between states; lookups inside the box then check nothing), and a second plan with the same
  weights collapses the rest;
* the EDD5 terrain (the configured one, or the top weight) and the weighted lateral slip.

`set_weights(w)` hands the kernels their `ModelBundle` for those weights. The planner calls `planned()` once a plan
runs on them (the lazy collapse then knows the weights held). Not while a plan runs (the lazily collapsed table is
rewritten in place): call both from one thread.
"""

from __future__ import annotations

import numba
import numpy as np

from gpmppi.gp.model_file import GPModel
from gpmppi.mppi.bundles import ModelBundle
from gpmppi.mppi.config import PlannerConfig
from gpmppi.mppi.dynamics import DYN_EDD5, DYN_GP, DYN_UNICYCLE, GP_EXACT, GP_GRID, GP_SIMPLEX
from gpmppi.mppi.gp_table import TABLE_AXES, collapse_into, collapse_weights, rollout_order, terrain_rows
from gpmppi.mppi.lazy_collapse import (
    block_keys,
    box_hull,
    collapse_slabs_at,
    empty_box,
    lazy_state,
    read_box,
    ready_box,
)

__all__ = ["TerrainTable"]

# `prepare` collapses ahead the slabs read by the plans of this many weight versions: the last plan's alone left ~320 of
# ~3,560 slabs a plan reads for it to collapse, the last four's 92 (for 18 % more slabs collapsed ahead)
READ_HISTORY = 4
# and the ready box is the box of the cells the last version's plans read alone: the hull of the last four versions'
# boxes held 6,720 slabs (p50, the bench's moving weights) for 0-2 cells of the next plan outside it, the last box
# 5,892 for 0-8 (those go through their stamps, and their slabs are collapsed ahead by the read history above)
READY_HISTORY = 1

_DYN = {"unicycle": DYN_UNICYCLE, "edd5": DYN_EDD5, "gp": DYN_GP}


class TerrainTable:
    """The terrain weights and the model the kernels read with them (grid table collapsed, or exact GP)."""

    def __init__(self, config: PlannerConfig, model: GPModel, backend: str) -> None:
        c = config
        if c.edd5_terrain is not None and c.edd5_terrain not in model.terrains:
            raise ValueError(f"edd5_terrain {c.edd5_terrain!r} is not a model terrain ({model.terrains})")
        self.terrains = list(model.terrains)
        self.backend = backend
        self.dyn = _DYN[c.dynamics]
        if c.gp_mode == "exact":
            self.gp_mode = GP_EXACT
        else:
            self.gp_mode = GP_SIMPLEX if c.grid_interpolation == "simplex" else GP_GRID
        m = len(self.terrains)
        self._edd5_index = None if c.edd5_terrain is None else self.terrains.index(c.edd5_terrain)
        self._theta = np.ascontiguousarray(model.theta, dtype=np.float64)
        self._noise = np.asarray(model.noise, dtype=np.float64).reshape(-1)
        self._edd5 = np.stack([np.asarray(model.edd5[t], dtype=np.float64) for t in model.terrains])
        self._lateral_full = model.lateral_matrix()
        self._table_full: np.ndarray | None = None
        # the model bundle's grid fields (the table itself collapsed per weights) and exact-GP fields
        self.grid = ModelBundle.no_grid()
        self.lazy_collapse = False
        self.read_history = READ_HISTORY
        self.ready_history = READY_HISTORY
        self.version = 1  # the version of the lazily collapsed table's weights (`lazy_collapse.ensure_block`)
        self._planned = False  # whether a plan has run with the weights of the table
        if self.dyn == DYN_GP and self.gp_mode != GP_EXACT:
            g = model.grid()
            self._table_full = terrain_rows(rollout_order(g.table))
            dims = np.array(g.table.shape[:4], dtype=np.int64)[TABLE_AXES]
            self.grid = {
                "table": self.grid["table"],
                "dims": dims,
                "lo": np.ascontiguousarray(np.asarray(g.lo, dtype=np.float64)[TABLE_AXES]),
                "inv_step": np.ascontiguousarray(np.asarray(g.inv_step, dtype=np.float64)[TABLE_AXES]),
                **ModelBundle.collapsed_whole(),
            }
            if c.table_collapse == "lazy":
                self.lazy_collapse = True
                # collapsed lazily, slab by slab as the rollouts reach them (`lazy_collapse.ensure_block`), into one
                # table kept for the planner's life; on CUDA the host reads only the nominal's slabs, and the
                # device collapses its own table whole from the same per-terrain rows (`cuda_backend`)
                self.grid.update(table=np.empty((int(np.prod(dims)), 4), dtype=np.float32),
                                 table_src=self._table_full, lazy=lazy_state(dims), collapse_w=np.zeros(4 + 4 * m))
                # the last version whose plan read each slab (0: none yet): `prepare` collapses ahead the slabs read
                # by the plans of the last `read_history` versions (`lazy_collapse.collapse_slabs_at`)
                self._last_read = np.zeros(block_keys(dims), dtype=np.int64)
        # (version, the box of the cells its plans read) of the last `read_history` versions: `prepare` collapses
        # ahead the hull of the last `ready_history` ones, the next version's ready box
        # (`lazy_collapse.collapse_slabs_at`)
        self._read_boxes: list[tuple[int, np.ndarray]] = []
        if self.dyn == DYN_GP and self.gp_mode == GP_EXACT:
            inv_ls = 1.0 / model.lengthscale
            self._ex = {
                "ex_scaled_x": np.ascontiguousarray(model.train_x[None, :, :] * inv_ls[:, None, :], dtype=np.float64),
                "ex_inv_ls": np.ascontiguousarray(inv_ls, dtype=np.float64),
                "ex_outputscale": np.ascontiguousarray(model.outputscale, dtype=np.float64),
                "ex_alpha": np.ascontiguousarray(model.alpha, dtype=np.float64),
                "ex_chol": np.ascontiguousarray(model.chol, dtype=np.float64),
            }
        else:
            self._ex = ModelBundle.no_exact(2 * m)
        self.weights: np.ndarray | None = None  # the weights the table is collapsed for (None: none yet)

    def check_weights(self, weights: np.ndarray | None) -> np.ndarray:
        """`weights` (M,) checked onto the simplex and renormalised; None: uniform."""
        m = len(self.terrains)
        if weights is None:
            return np.full(m, 1.0 / m)
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if w.shape != (m,):
            raise ValueError(f"weights must have one entry per terrain {self.terrains}, got shape {w.shape}")
        if not np.all(np.isfinite(w)) or np.any(w < -1e-6) or abs(w.sum() - 1.0) > 1e-4:
            raise ValueError(f"weights must lie on the simplex (>= 0, sum 1), got {w.tolist()}")
        w = np.clip(w, 0.0, None)
        return w / w.sum()

    def set_weights(self, w: np.ndarray, ahead: bool = False) -> ModelBundle:
        """The kernels' model for the (checked) weights `w`: collapse the grid table when they changed (lazily: mark
        it stale, `lazy_collapse.ensure_block`; `ahead`: collapse the slabs the last plans read now), pick the EDD5
        terrain."""
        changed = self.weights is None or not np.array_equal(w, self.weights)
        if self._table_full is not None and self.lazy_collapse:
            lazy = self.grid["lazy"]
            if changed:  # every slab stale: the readers collapse those they read
                self.grid["collapse_w"][:] = collapse_weights(w, self.noise_var(w))
                self.version += 1
                since = max(1, self.version - self.read_history)
                # the box of the cells the last version's plans read joins the history; the boxes of the versions
                # since `since` stay
                self._read_boxes = [(v, b) for v, b in self._read_boxes if v >= since]
                self._read_boxes.append((self.version - 1, read_box(lazy).copy()))
                ready = empty_box()
                if ahead:  # `prepare`: the slabs the last plans read, now; a lookup in their hull checks nothing
                    ready = box_hull([b for v, b in self._read_boxes if v >= self.version - self.ready_history])
                    collapse_slabs_at(lazy, self._table_full, self.grid["collapse_w"], self.grid["table"],
                                      self.grid["dims"], self.version - 1, self.version, numba.get_num_threads(),
                                      self._last_read, since, ready)
                ready_box(lazy)[:] = ready
                read_box(lazy)[:] = empty_box()
                lazy[0] = self.version
            elif lazy[0] != 0 and self._planned and self.backend == "cpu":
                # the weights held for a second plan: collapse the rest of the table now (the slabs already current
                # get the same bits again), and the rollouts skip their slab checks until the weights move
                collapse_into(self._table_full, self.grid["collapse_w"], self.grid["table"])
                lazy[0] = 0
        elif self._table_full is not None and changed:
            # predictive variance = latent + likelihood noise: the rollouts' variance cost and the propagated
            # covariance both read it from the table
            table = np.empty((self._table_full.shape[0], 4), dtype=np.float32)
            collapse_into(self._table_full, collapse_weights(w, self.noise_var(w)), table)
            self.grid = {**self.grid, "table": table}
        if changed:
            self.weights = w.copy()
            self._planned = False
        # the sideways slide is linear in its coefficients, so the ensemble's is the weighted sum (GP model only)
        lateral = w @ self._lateral_full if self.dyn == DYN_GP else np.zeros(2)
        idx = self._edd5_index if self._edd5_index is not None else int(np.argmax(w))
        return ModelBundle(dyn_mode=self.dyn, theta=self._theta, lateral=lateral, edd5=self._edd5[idx],
                           gp_mode=self.gp_mode, **self.grid, **self._ex, terrain_w=w)

    def planned(self) -> None:
        """A plan runs on the weights of the last `set_weights`."""
        self._planned = True

    def noise_var(self, w: np.ndarray) -> tuple[float, float]:
        """Ensemble likelihood noise (sum_i w_i^2 noise_i for v and omega); zero for the models without a GP.

        The GP's latent variance C says how unsure the mean is; the next velocity itself scatters by
        C + noise (the predictive variance), and that is what the chance constraints must cover.
        """
        if self.dyn != DYN_GP:
            return 0.0, 0.0
        w2 = w * w
        return float(w2 @ self._noise[0::2]), float(w2 @ self._noise[1::2])

    def exact_noise_var(self, w: np.ndarray) -> tuple[float, float]:
        """The noise the kernels do not add themselves: the exact GP gives latent variances (the grid table has it)."""
        return self.noise_var(w) if self.gp_mode == GP_EXACT else (0.0, 0.0)
