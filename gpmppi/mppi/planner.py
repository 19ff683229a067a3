"""GP-MPPI planner: configuration, one planning iteration, and its result.

One iteration: (1) propagate mean and covariance along the warm-started (shifted) previous
optimal sequence and tighten the lane / inflate the obstacles with them; (2) roll out S noisy
copies of the sequence over the horizon with the chosen model and score them (one kernel);
(3) softmax-weight the samples with the temperature and update the sequence; optional
Savitzky-Golay smoothing and acceleration limits, then control limits; (4) report the nominal
trajectory of the new sequence with its covariances and tightened bounds; (5) shift for the
next call. All baselines (`unicycle`, `edd5`) use exactly the same costs and settings.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from math import pi
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.signal import savgol_filter

from gpmppi.costs import N_COST_WEIGHTS, W_VARIANCE, ChanceQuantiles, inflate_obstacles, tighten_lane
from gpmppi.gp.model_file import GPModel
from gpmppi.mppi import backends
from gpmppi.mppi.dynamics import (
    DYN_EDD5,
    DYN_GP,
    DYN_UNICYCLE,
    GP_EXACT,
    GP_GRID,
    GP_SIMPLEX,
    TABLE_AXES,
    collapse_table,
    propagate,
    rollout_order,
)
from gpmppi.mppi.lane import LaneLookup, cached_lane_lookup
from gpmppi.tasks import GoalTask, LaneTask

_DYN = {"unicycle": DYN_UNICYCLE, "edd5": DYN_EDD5, "gp": DYN_GP}


class PlannerConfig(BaseModel):
    """Every setting of the planner; the same costs and settings apply to every dynamics choice."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    dynamics: Literal["gp", "edd5", "unicycle"] = Field(
        "gp", description="Rollout model: nominal dynamic unicycle + GP ensemble residual, EDD5, or kinematic unicycle"
    )
    gp_mode: Literal["grid", "exact"] = Field("grid", description="GP evaluation: interpolated grid table or exact GP")
    grid_interpolation: Literal["simplex", "multilinear"] = Field(
        "simplex",
        description="Grid GP interpolation: simplex (5 nodes, ~3x faster on tables larger than the caches) or "
        "multilinear (16 nodes, as gpmppi.gp.grid_interp); both exact at the nodes and second-order accurate",
    )
    backend: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="Kernels: numba CPU, numba CUDA (grid GP only), or auto (CUDA when numba finds a GPU)"
    )
    samples: int = Field(1024, ge=1, description="Number of sampled control sequences S")
    horizon: int = Field(40, ge=1, description="Horizon N [steps]")
    dt: float = Field(0.1, gt=0, description="Step of the rollouts [s]")
    temperature: float = Field(1.0, gt=0, description="MPPI temperature lambda of the softmax over costs")
    noise_std: tuple[float, float] = Field((1.0, 1.0), description="Control noise std [m/s, rad/s]")
    v_limits: tuple[float, float] = Field((0.0, 2.0), description="Commanded linear speed limits [m/s]")
    omega_limits: tuple[float, float] = Field((-pi, pi), description="Commanded yaw-rate limits [rad/s]")
    accel_limits: tuple[float, float] | None = Field(
        None, description="Optional |dv_ref/dt|, |domega_ref/dt| limits along the sequence [m/s^2, rad/s^2]"
    )
    smoothing_window: int = Field(0, ge=0, description="Savitzky-Golay window over the sequence (0 = off; odd)")
    smoothing_order: int = Field(2, ge=0, description="Savitzky-Golay polynomial order")
    p_x: float = Field(0.95, gt=0, lt=1, description="Probability of the chance constraints")
    tightening: bool = Field(True, description="Tighten the lane / inflate obstacles with the propagated covariance")
    min_half_width_fraction: float = Field(
        0.1, gt=0, le=1, description="Tightened lane half-width never goes below this fraction of the half-width"
    )
    max_inflation: float = Field(1.0, ge=0, description="Cap on the covariance inflation of obstacle radii [m]")
    robot_radius: float = Field(0.0, ge=0, description="Added to every obstacle radius [m]")
    step_clearance: bool = Field(
        True,
        description="Grow each (inflated) obstacle radius r to sqrt(r^2 + (v_max dt / 2)^2): collisions are checked "
        "only at the rollout steps, and with this radius the straight path between two steps (at most v_max dt "
        "long) cannot cut into the circle r either",
    )
    seed: int = Field(0, ge=0, lt=2**63, description="Seed of the sampling noise (identical seeds, identical plans)")
    edd5_terrain: str | None = Field(
        None, description="Terrain of the EDD5 model; None = the terrain with the largest weight"
    )
    initial_control: tuple[float, float] = Field((0.0, 0.0), description="Sequence at start and appended on shift")
    sample_output: int = Field(32, ge=0, description="How many rollouts' XY to return for display")
    lane_cell: float = Field(0.1, gt=0, description="Cell of the lane nearest-segment lookup grid [m]")
    # lane weights: with r the lane half-width (1.75-2.75 m), 300 (d / r)^2 prices a 5 cm deviation like a 0.15 m/s
    # speed shortfall under w_speed = 2; at (2, 1) tracking error was free next to speed (70-150 mm RMSE)
    w_variance: float = Field(
        1.0, ge=0, description="Weight of the GP variance cost (every step); 10 made GP-MPPI ~15% slower to goals"
    )
    w_deviation: float = Field(300.0, ge=0, description="Weight of the normalised lane deviation (d / r)^2")
    w_slip: float = Field(0.1, ge=0, description="Weight of the command-vs-velocity gap (slip)")
    w_lane_exit: float = Field(1000.0, ge=0, description="Weight of leaving the tightened lane (times discount^k)")
    lane_exit_discount: float = Field(0.9, gt=0, le=1, description="Discount per step of the lane-exit indicator")
    w_speed: float = Field(2.0, ge=0, description="Weight of (v - speed_target)^2")
    w_collision: float = Field(1000.0, ge=0, description="Weight of being inside an inflated obstacle")
    w_goal: float = Field(1.0, ge=0, description="Weight of the distance to the goal at every step")
    w_terminal: float = Field(10.0, ge=0, description="Weight of the distance to the goal at the horizon's end")

    @model_validator(mode="after")
    def _check(self) -> PlannerConfig:
        for name in ("v_limits", "omega_limits"):
            lo, hi = getattr(self, name)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                raise ValueError(f"{name} must be finite with low < high, got {(lo, hi)}")
        if any(not np.isfinite(s) or s < 0 for s in self.noise_std):
            raise ValueError(f"noise_std must be finite and >= 0, got {self.noise_std}")
        if self.accel_limits is not None and any(not np.isfinite(a) or a <= 0 for a in self.accel_limits):
            raise ValueError(f"accel_limits must be positive, got {self.accel_limits}")
        if self.smoothing_window:
            if self.smoothing_window % 2 == 0 or self.smoothing_window <= self.smoothing_order:
                raise ValueError("smoothing_window must be odd and larger than smoothing_order")
            if self.smoothing_window > self.horizon:
                raise ValueError("smoothing_window must not exceed the horizon")
        return self

    def cost_weights(self) -> np.ndarray:
        w = np.array([
            self.w_variance, self.w_deviation, self.w_slip, self.w_lane_exit, self.w_speed,
            self.w_collision, self.w_goal, self.w_terminal, self.lane_exit_discount,
        ])
        assert w.shape == (N_COST_WEIGHTS,)
        return w


@dataclass
class PlanResult:
    control: np.ndarray  # (2,) [v_ref, omega_ref] to apply now (always finite)
    controls: np.ndarray  # (N, 2) optimal sequence
    states: np.ndarray  # (N+1, 5) nominal trajectory
    covariances: np.ndarray  # (N+1, 5, 5)
    tightened: np.ndarray  # lane: (N+1,) tightened half-width; goal: (N+1, K) inflated obstacle radii
    sample_states: np.ndarray  # (k, N+1, 2) XY of a subset of rollouts
    sample_costs: np.ndarray  # (k,)
    cost: float  # cost of the nominal sequence under the constraints used this iteration
    weights: np.ndarray  # (M,) terrain weights used
    timings_ms: dict[str, float]
    flags: dict[str, int] = field(default_factory=dict)  # clamps and safe fallbacks of this iteration


class Planner:
    """GP-MPPI over a `GPModel`; `plan` is one receding-horizon iteration (warm-started)."""

    def __init__(self, config: PlannerConfig, model: GPModel) -> None:
        self.config = config
        self.model = model
        c = config
        m = len(model.terrains)
        if c.edd5_terrain is not None and c.edd5_terrain not in model.terrains:
            raise ValueError(f"edd5_terrain {c.edd5_terrain!r} is not a model terrain ({model.terrains})")
        exact_gp = c.dynamics == "gp" and c.gp_mode == "exact"
        if exact_gp and c.backend == "cuda":
            raise ValueError("backend='cuda' evaluates the GP by grid only; use gp_mode='grid' or backend='cpu'")
        self.backend = "cpu" if exact_gp else backends.resolve(c.backend)
        self._dyn = _DYN[c.dynamics]
        if c.gp_mode == "exact":
            self._gp_mode = GP_EXACT
        else:
            self._gp_mode = GP_SIMPLEX if c.grid_interpolation == "simplex" else GP_GRID
        self._theta = np.ascontiguousarray(model.theta, dtype=np.float64)
        self._noise = np.asarray(model.noise, dtype=np.float64).reshape(-1)
        self._edd5 = np.stack([np.asarray(model.edd5[t], dtype=np.float64) for t in model.terrains])
        self._quant = ChanceQuantiles.for_probability(c.p_x)
        self._cost_w = c.cost_weights()
        self._u_lo = np.array([c.v_limits[0], c.omega_limits[0]])
        self._u_hi = np.array([c.v_limits[1], c.omega_limits[1]])
        self._std = np.array(c.noise_std, dtype=np.float64)
        self._table_full: np.ndarray | None = None
        self._table = np.zeros((16, 4), dtype=np.float32)
        self._table_dims = np.full(4, 2, dtype=np.int64)
        self._grid_lo = np.zeros(4)
        self._grid_inv = np.ones(4)
        if self._dyn == DYN_GP and self._gp_mode != GP_EXACT:
            g = model.grid()
            self._table_full = rollout_order(g.table)
            self._table_dims = np.array(g.table.shape[:4], dtype=np.int64)[TABLE_AXES]
            self._grid_lo = np.ascontiguousarray(np.asarray(g.lo, dtype=np.float64)[TABLE_AXES])
            self._grid_inv = np.ascontiguousarray(np.asarray(g.inv_step, dtype=np.float64)[TABLE_AXES])
        if self._dyn == DYN_GP and self._gp_mode == GP_EXACT:
            inv_ls = 1.0 / model.lengthscale
            self._ex = (
                np.ascontiguousarray(model.train_x[None, :, :] * inv_ls[:, None, :]),
                np.ascontiguousarray(inv_ls),
                np.ascontiguousarray(model.outputscale),
                np.ascontiguousarray(model.alpha),
                np.ascontiguousarray(model.chol),
            )
        else:
            self._ex = (np.zeros((2 * m, 1, 4)), np.ones((2 * m, 4)), np.zeros(2 * m), np.zeros((2 * m, 1)),
                        np.ones((2 * m, 1, 1)))
        self._table_weights: np.ndarray | None = None
        self._lane_key: tuple | None = None
        self._lane: LaneLookup | None = None
        self.reset()

    def reset(self) -> None:
        """Forget the warm start, the last control and the iteration counter (plans repeat from here)."""
        c = self.config
        self._nominal = np.tile(np.clip(np.array(c.initial_control, dtype=np.float64), self._u_lo, self._u_hi),
                                (c.horizon, 1))
        self._last_control: np.ndarray | None = None
        self._iteration = 0

    # ---------------------------------------------------------------- inputs
    def _check_inputs(self, state: np.ndarray, task: LaneTask | GoalTask, weights: np.ndarray | None) -> tuple:
        x = np.asarray(state, dtype=np.float64).reshape(-1)
        if x.shape != (5,):
            raise ValueError(f"state must be [X, Y, theta, v, omega] (5 numbers), got shape {np.shape(state)}")
        if not np.all(np.isfinite(x)):
            raise ValueError(f"state must be finite, got {x.tolist()}; drop this state and wait for the next one")
        if not isinstance(task, (LaneTask, GoalTask)):
            raise ValueError(f"task must be a LaneTask or GoalTask, got {type(task).__name__}")
        m = len(self.model.terrains)
        if weights is None:
            w = np.full(m, 1.0 / m)
        else:
            w = np.asarray(weights, dtype=np.float64).reshape(-1)
            if w.shape != (m,):
                raise ValueError(f"weights must have one entry per terrain {self.model.terrains}, got shape {w.shape}")
            if not np.all(np.isfinite(w)) or np.any(w < -1e-6) or abs(w.sum() - 1.0) > 1e-4:
                raise ValueError(f"weights must lie on the simplex (>= 0, sum 1), got {w.tolist()}")
            w = np.clip(w, 0.0, None)
            w = w / w.sum()
        if isinstance(task, GoalTask):
            o = task.obstacles
            if o.shape[0]:
                d = np.hypot(o[:, 0] - task.goal[0], o[:, 1] - task.goal[1])
                inside = np.nonzero(d < o[:, 2] + self.config.robot_radius)[0]
                if inside.size:
                    raise ValueError(
                        f"task.goal {task.goal.tolist()} lies inside obstacle {int(inside[0])} "
                        f"{o[inside[0]].tolist()}; move the goal out of the obstacles"
                    )
        return np.ascontiguousarray(x), w

    def _lane_lookup(self, task: LaneTask) -> LaneLookup:
        key = (task.centerline.shape, hash(task.centerline.tobytes()), task.closed)
        if key != self._lane_key:
            c = self.config
            reach = c.horizon * c.dt * max(abs(c.v_limits[0]), abs(c.v_limits[1]))
            margin = task.half_width + min(reach, 10.0) + 1.0
            self._lane = cached_lane_lookup(task.centerline, task.closed, margin, c.lane_cell)
            self._lane_key = key
        assert self._lane is not None
        return self._lane

    def _terrain_setup(self, w: np.ndarray) -> tuple[np.ndarray, float]:
        """Collapse the grid table when the weights changed; pick the EDD5 terrain. Returns (edd5_p, ms)."""
        t0 = time.perf_counter()
        if self._table_full is not None and (self._table_weights is None or not np.array_equal(w, self._table_weights)):
            # predictive variance = latent + likelihood noise: the rollouts' variance cost and the propagated
            # covariance both read it from the table
            self._table = collapse_table(self._table_full, w, self._noise_var(w), ordered=True).reshape(-1, 4)
            self._table_weights = w.copy()
        name = self.config.edd5_terrain
        idx = self.model.terrains.index(name) if name is not None else int(np.argmax(w))
        return self._edd5[idx], (time.perf_counter() - t0) * 1e3

    def _noise_var(self, w: np.ndarray) -> tuple[float, float]:
        """Ensemble likelihood noise (sum_i w_i^2 noise_i for v and omega); zero for the models without a GP.

        The GP's latent variance C says how unsure the mean is; the next velocity itself scatters by
        C + noise (the predictive variance), and that is what the chance constraints must cover.
        """
        if self._dyn != DYN_GP:
            return 0.0, 0.0
        w2 = w * w
        return float(w2 @ self._noise[0::2]), float(w2 @ self._noise[1::2])

    def _propagate(self, x: np.ndarray, controls: np.ndarray, edd5_p: np.ndarray, w: np.ndarray) -> tuple:
        return propagate(x, controls, self.config.dt, self._dyn, self._theta, edd5_p, self._gp_mode, self._table,
                         self._table_dims, self._grid_lo, self._grid_inv, *self._ex, w, *self._exact_noise_var(w))

    def _exact_noise_var(self, w: np.ndarray) -> tuple[float, float]:
        """The noise the kernels do not add themselves: the exact GP gives latent variances (the grid table has it)."""
        return self._noise_var(w) if self._gp_mode == GP_EXACT else (0.0, 0.0)

    def _bounds(self, task: LaneTask | GoalTask, states: np.ndarray, covs: np.ndarray) -> tuple[np.ndarray, int]:
        """Tightened half-widths (N+1,) or effective obstacle radii (N+1, K), and the clamp count."""
        c = self.config
        if not c.tightening:
            covs = np.zeros_like(covs)
        if isinstance(task, LaneTask):
            return tighten_lane(covs, float(task.half_width), self._quant.chi2_2, c.min_half_width_fraction)
        radii, capped = inflate_obstacles(states, covs, task.obstacles, self._quant.normal, c.robot_radius,
                                          c.max_inflation)
        if c.step_clearance:
            half_step = 0.5 * c.dt * max(abs(c.v_limits[0]), abs(c.v_limits[1]))
            radii = np.sqrt(radii * radii + half_step * half_step)
        return radii, capped

    # ---------------------------------------------------------------- plan
    def plan(self, state: np.ndarray, task: LaneTask | GoalTask, weights: np.ndarray | None = None) -> PlanResult:
        """One MPPI iteration from `state` for `task` with terrain `weights` (None = uniform)."""
        c = self.config
        t_start = time.perf_counter()
        x, w = self._check_inputs(state, task, weights)
        edd5_p, collapse_ms = self._terrain_setup(w)
        t0 = time.perf_counter()
        nominal = self._nominal
        prev_states, prev_covs, _ = self._propagate(x, nominal, edd5_p, w)
        bounds, clamped_before = self._bounds(task, prev_states, prev_covs)
        t1 = time.perf_counter()

        is_lane = isinstance(task, LaneTask)
        if is_lane:
            lane = self._lane_lookup(task)
            task_arrays = backends.TaskArrays.for_lane(lane, float(task.half_width), bounds, float(task.speed_target))
        else:
            task_arrays = backends.TaskArrays.for_goal(task.goal, task.obstacles, bounds)
        model_arrays = backends.ModelArrays(
            self._dyn, self._theta, edd5_p, self._gp_mode, self._table, self._table_dims, self._grid_lo, self._grid_inv,
            self._ex, w,
        )
        n_xy = min(c.sample_output, c.samples)
        eps, costs, xy = backends.rollouts(
            self.backend, x, nominal, self._std, self._u_lo, self._u_hi, c.dt, c.seed, self._iteration,
            model_arrays, task_arrays, self._cost_w, c.samples, n_xy,
        )
        # exact GP: the kernels' variance cost is latent; the noise adds the same to every rollout (the update
        # is unchanged), added here so that costs are those of the predictive variance in every mode
        noise_cost = c.horizon * self._cost_w[W_VARIANCE] * sum(self._exact_noise_var(w))
        costs = costs + noise_cost
        t2 = time.perf_counter()

        new_u, _sample_w = backends.softmax_update(nominal, eps, costs, c.temperature)
        flags: dict[str, int] = {"all_costs_infinite": int(not np.any(np.isfinite(costs)))}
        new_u = self._shape_sequence(new_u)
        t3 = time.perf_counter()

        states, covs, _ = self._propagate(x, new_u, edd5_p, w)
        out_bounds, clamped_after = self._bounds(task, states, covs)
        _, nominal_cost, _ = backends.rollouts(
            "cpu", x, new_u, np.zeros(2), self._u_lo, self._u_hi, c.dt, c.seed, self._iteration,
            model_arrays, task_arrays, self._cost_w, 1, 0,
        )
        nominal_cost = nominal_cost + noise_cost
        t4 = time.perf_counter()

        control = new_u[0].copy()
        if not np.all(np.isfinite(new_u)):
            # never hand out a non-finite command: stop, and start the sequence afresh
            flags["nonfinite_fallback"] = 1
            new_u = np.tile(np.clip(np.zeros(2), self._u_lo, self._u_hi), (c.horizon, 1))
            control = new_u[0].copy()
            states = np.repeat(x[None, :], c.horizon + 1, axis=0)
            covs = np.zeros_like(covs)
            out_bounds, clamped_after = self._bounds(task, states, covs)
        else:
            flags["nonfinite_fallback"] = 0
        key = "half_width_clamped_steps" if is_lane else "inflation_capped"
        flags[key] = int(clamped_before)
        flags[key + "_plan"] = int(clamped_after)
        self._last_control = control
        self._nominal = np.concatenate([new_u[1:], new_u[-1:]], axis=0)
        self._iteration += 1
        t_end = time.perf_counter()
        return PlanResult(
            control=control,
            controls=new_u,
            states=states,
            covariances=covs,
            tightened=out_bounds,
            sample_states=xy,
            sample_costs=costs[:n_xy].copy(),
            cost=float(nominal_cost[0]),
            weights=w,
            timings_ms={
                "total": (t_end - t_start) * 1e3,
                "collapse": collapse_ms,
                "tighten": (t1 - t0) * 1e3,
                "rollouts": (t2 - t1) * 1e3,
                "update": (t3 - t2) * 1e3,
                "nominal": (t4 - t3) * 1e3,
            },
            flags=flags,
        )

    def _shape_sequence(self, u: np.ndarray) -> np.ndarray:
        """Optional smoothing, then acceleration limits from the last applied control, then control limits."""
        c = self.config
        if c.smoothing_window:
            u = savgol_filter(u, c.smoothing_window, c.smoothing_order, axis=0, mode="nearest")
        if c.accel_limits is not None:
            step = np.array(c.accel_limits) * c.dt
            prev = self._last_control
            u = u.copy()
            for k in range(u.shape[0]):
                if prev is not None:
                    u[k] = np.clip(u[k], prev - step, prev + step)
                prev = u[k]
        return np.ascontiguousarray(np.clip(u, self._u_lo, self._u_hi))
