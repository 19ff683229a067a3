"""Backend selection and the one call the planner makes per iteration: `rollouts`.

Both backends take the same arrays and draw the same noise, so they agree to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpmppi.mppi.cpu_backend import TASK_GOAL, TASK_LANE, rollout_kernel, softmax_update
from gpmppi.mppi.goal_field import GoalField
from gpmppi.mppi.lane import LaneLookup

__all__ = ["ModelArrays", "TaskArrays", "resolve", "rollouts", "softmax_update"]


def cuda_available() -> bool:
    try:
        from numba import cuda

        return bool(cuda.is_available())
    except Exception:  # a broken driver install means: no CUDA
        return False


def resolve(backend: str) -> str:
    """'auto' -> 'cuda' when numba sees a GPU (or the simulator), else 'cpu'; 'cuda' without one is an error."""
    if backend == "cpu":
        return "cpu"
    if backend == "cuda":
        if not cuda_available():
            raise ValueError("backend='cuda' but numba.cuda finds no GPU; use backend='cpu' or 'auto'")
        return "cuda"
    if backend == "auto":
        return "cuda" if cuda_available() else "cpu"
    raise ValueError(f"backend must be 'auto', 'cpu' or 'cuda', got {backend!r}")


@dataclass
class ModelArrays:
    dyn_mode: int
    theta: np.ndarray
    lateral: np.ndarray  # (2,) terrain-weighted lateral slip coefficients (`gpmppi.models.lateral_slip`)
    edd5_p: np.ndarray
    gp_mode: int
    table: np.ndarray  # (nodes, 4) float32 collapsed GP table
    dims: np.ndarray  # (4,) int64 grid nodes per axis
    lo: np.ndarray
    inv_step: np.ndarray
    exact: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # scaled_x, inv_ls, os, alpha, chol
    terrain_w: np.ndarray


_NO_SEG = np.zeros((1, 5))
_NO_SEG[0, 4] = 1.0
_NO_START = np.zeros(2, dtype=np.int64)
_NO_CAND = np.zeros(0, dtype=np.int32)
_NO_FIELD = np.zeros((1, 1, 3))


@dataclass
class TaskArrays:
    kind: int
    seg: np.ndarray
    cell_start: np.ndarray
    candidates: np.ndarray
    field: np.ndarray
    grid_origin: np.ndarray
    inv_cell: float
    half_width: float
    tightened_hw: np.ndarray
    speed_target: float
    goal: np.ndarray
    obstacles: np.ndarray
    radii: np.ndarray

    @classmethod
    def for_lane(cls, lane: LaneLookup, half_width: float, tightened: np.ndarray, speed: float) -> TaskArrays:
        return cls(TASK_LANE, lane.segments, lane.cell_start, lane.candidates, lane.field, lane.origin, lane.inv_cell,
                   half_width,
                   np.ascontiguousarray(tightened), speed, np.zeros(2), np.zeros((0, 3)),
                   np.zeros((tightened.shape[0], 0)))

    @classmethod
    def for_goal(
        cls, goal: np.ndarray, obstacles: np.ndarray, radii: np.ndarray, goal_field: GoalField | None
    ) -> TaskArrays:
        """`goal_field` None: no geodesic field (the cost weights must then select the straight-line distance)."""
        field, origin, inv_cell = (
            (_NO_FIELD, np.zeros(2), 1.0) if goal_field is None
            else (goal_field.field, goal_field.origin, goal_field.inv_cell)
        )
        return cls(TASK_GOAL, _NO_SEG, _NO_START, _NO_CAND, field, origin, inv_cell, 1.0,
                   np.ones(radii.shape[0]), 0.0,
                   np.ascontiguousarray(goal, dtype=np.float64), np.ascontiguousarray(obstacles, dtype=np.float64),
                   np.ascontiguousarray(radii))


def rollouts(
    backend: str, x0: np.ndarray, nominal: np.ndarray, noise_std: np.ndarray, u_lo: np.ndarray, u_hi: np.ndarray,
    dt: float, seed: int, iteration: int, m: ModelArrays, t: TaskArrays, cost_w: np.ndarray, samples: int, n_xy: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Perturbations (S, N, 2) float32, costs (S,), XY of the first n_xy rollouts (n_xy, N+1, 2)."""
    horizon = nominal.shape[0]
    eps = np.empty((samples, horizon, 2), dtype=np.float32)
    costs = np.empty(samples)
    xy = np.empty((n_xy, horizon + 1, 2))
    args = (
        x0, np.ascontiguousarray(nominal), noise_std, u_lo, u_hi, float(dt), int(seed), int(iteration),
        m.dyn_mode, m.theta, m.lateral, m.edd5_p, m.gp_mode, m.table, m.dims, m.lo, m.inv_step, *m.exact, m.terrain_w,
        t.kind, t.seg, t.cell_start, t.candidates, t.field, t.grid_origin, float(t.inv_cell), float(t.half_width),
        t.tightened_hw, float(t.speed_target), t.goal, t.obstacles, t.radii, cost_w,
    )
    if backend == "cuda":
        from gpmppi.mppi.cuda_backend import cuda_rollouts

        cuda_rollouts(args, eps, costs, xy)
    else:
        rollout_kernel(*args, eps, costs, xy)
    return eps, costs, xy
