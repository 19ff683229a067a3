"""Planner configuration: every setting of the GP-MPPI planner, validated (pydantic, frozen).

The same costs and settings apply to every dynamics choice, so the baselines are fair.
"""

from __future__ import annotations

from collections.abc import Mapping
from math import pi
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from gpmppi.mppi.bundles import CostBundle
from gpmppi.mppi.critics.settings import CRITIC_KEYS, critic_settings, critic_weights
from gpmppi.mppi.rng import noise_memory

__all__ = ["DEFAULT_SMOOTHING_WINDOW", "PlannerConfig"]

# update=smooth's Savitzky-Golay window [steps] unless one is set: 9 won the comparison in docs/smooth_commands.md
DEFAULT_SMOOTHING_WINDOW = 9


class PlannerConfig(BaseModel):
    """Every setting of the planner; the same costs and settings apply to every dynamics choice."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    dynamics: Literal["gp", "edd5", "unicycle"] = Field(
        "gp", description="Rollout model: nominal dynamic unicycle + GP ensemble residual, EDD5, or kinematic unicycle"
    )
    gp_mode: Literal["grid", "exact"] = Field("grid", description="GP evaluation: interpolated grid table or exact GP")
    grid_interpolation: Literal["simplex", "multilinear"] = Field(
        "simplex",
        description="Grid GP interpolation: simplex (5 table nodes per lookup) or multilinear (16 nodes, as "
        "gpmppi.gp.grid_interp); both exact at the nodes and second-order accurate (docs/planner_config.md)",
    )
    table_collapse: Literal["lazy", "whole"] = Field(
        "lazy",
        description="Grid GP on the CPU: collapse the table for new terrain weights slab by slab as the rollouts "
        "reach them (lazy) or all of it at once (whole); the plans are identical, lazy is cheaper when the weights "
        "move every cycle. On CUDA: lazy collapses the device's table on the device (the host's lazily, for the "
        "nominal), whole collapses on the host and uploads the table",
    )
    backend: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="Kernels: numba CPU, numba CUDA (grid GP only), or auto (CUDA when numba finds a GPU)"
    )
    samples: int = Field(1024, ge=1, description="Number of sampled control sequences S")
    horizon: int = Field(40, ge=1, description="Horizon N [steps]")
    dt: float = Field(0.1, gt=0, description="Step of the rollouts [s]")
    update: Literal["smooth", "paper"] = Field(
        "smooth",
        description="MPPI update: `smooth` picks each update's temperature so that the softmax's effective sample "
        "size is `effective_sample_fraction` of the samples and smooths the sequence (`smoothing_window`); `paper` "
        "is the paper's form: the fixed `temperature`, no smoothing (docs/smooth_commands.md)",
    )
    temperature: float = Field(
        1.0, gt=0, description="MPPI temperature lambda of the softmax over costs (update=paper; update=smooth uses "
        "it only when every finite cost is the same)",
    )
    effective_sample_fraction: float = Field(
        0.05, gt=0, le=1,
        description="update=smooth: the effective sample size (Kish) each update's temperature is chosen for, as a "
        "fraction of the samples",
    )
    sampling: Literal["white", "coloured"] = Field(
        "white",
        description="Noise of the sampled sequences: `white` (independent per step, as in the paper) or `coloured` "
        "(AR(1) in time, each step N(0, noise_std^2), correlation falling by 1/e in `noise_correlation_time`)",
    )
    noise_correlation_time: float = Field(
        0.5, gt=0, description="sampling=coloured: time over which the noise's correlation falls to 1/e [s]"
    )
    noise_std: tuple[float, float] = Field(
        (1.0, 1.0), description="Control noise std [m/s, rad/s] (goal tasks; lanes use `lane_noise_std`)"
    )
    lane_noise_std: tuple[float, float] | None = Field(
        (0.5, 0.7),
        description="Control noise std for lane tasks [m/s, rad/s] (None = noise_std)",
    )
    v_limits: tuple[float, float] = Field((0.0, 2.0), description="Commanded linear speed limits [m/s]")
    omega_limits: tuple[float, float] = Field((-pi, pi), description="Commanded yaw-rate limits [rad/s]")
    accel_limits: tuple[float, float] | None = Field(
        None,
        description="Optional |dv_ref/dt|, |domega_ref/dt| limits [m/s^2, rad/s^2] of the command sent, from one plan "
        "to the next: every sampled sequence's first command keeps them from the command in effect, so the update "
        "chooses within them (None: none; docs/smooth_commands.md has what they cost)",
    )
    smoothing_window: int | None = Field(
        None, ge=0,
        description="Savitzky-Golay window over the updated sequence [steps] (odd; 0 = off; None = 9 under "
        "update=smooth, limited to the horizon, and off under update=paper)",
    )
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
        description="Grow each (inflated) obstacle radius r to sqrt(r^2 + (v_max dt / 2)^2) [m], so that the straight "
        "path between two rollout steps (at most v_max dt long) cannot cut into the circle r",
    )
    state_std: tuple[float, float, float, float, float] = Field(
        (0.005, 0.005, 0.003, 0.008, 0.01),
        description="Std of the state estimate [x m, y m, yaw rad, v m/s, omega rad/s]: the start covariance of the "
        "propagation (GP model) when `plan` gets no covariance",
    )
    seed: int = Field(0, ge=0, lt=2**63, description="Seed of the sampling noise (identical seeds, identical plans)")
    edd5_terrain: str | None = Field(
        None, description="Terrain of the EDD5 model; None = the terrain with the largest weight"
    )
    initial_control: tuple[float, float] = Field((0.0, 0.0), description="Sequence at start and appended on shift")
    sample_output: int = Field(32, ge=0, description="How many rollouts' XY to return for display")
    lane_cell: float = Field(0.1, gt=0, description="Cell of the lane nearest-segment lookup grid [m]")
    critics: dict[str, dict[str, Any]] = Field(
        default_factory=dict, validate_default=True,
        description="The critics (cost terms) by name: `{name: {weight, enabled, tasks, <its parameters>}}`, each key "
        "optional (the critic's default); see docs/planner_config.md for the critics, their defaults and parameters",
    )
    goal_distance: Literal["geodesic", "euclidean"] = Field(
        "geodesic",
        description="Distance of the goal critics: the shortest path around the obstacles or the straight line as "
        "in the paper",
    )
    goal_cell: float = Field(0.1, gt=0, description="Cell of the geodesic goal-distance grid [m]")

    @field_validator("critics", mode="before")
    @classmethod
    def _complete_critics(cls, raw: Any) -> dict[str, dict[str, Any]]:
        if raw is not None and not isinstance(raw, Mapping):
            raise ValueError(f"critics must be a mapping of critic name to its settings, got {raw!r}")
        return critic_settings(raw)

    @model_validator(mode="after")
    def _check(self) -> PlannerConfig:
        for name in ("v_limits", "omega_limits"):
            lo, hi = getattr(self, name)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                raise ValueError(f"{name} must be finite with low < high, got {(lo, hi)}")
        if any(not np.isfinite(s) or s < 0 for s in self.state_std):
            raise ValueError(f"state_std must be finite and >= 0, got {self.state_std}")
        for name in ("noise_std", "lane_noise_std"):
            std = getattr(self, name)
            if std is not None and any(not np.isfinite(s) or s < 0 for s in std):
                raise ValueError(f"{name} must be finite and >= 0, got {std}")
        if self.accel_limits is not None and any(not np.isfinite(a) or a <= 0 for a in self.accel_limits):
            raise ValueError(f"accel_limits must be positive and finite [m/s^2, rad/s^2], got "
                             f"{list(self.accel_limits)}; leave it out for none")
        window = self.smoothing_window
        if window:
            if window % 2 == 0 or window <= self.smoothing_order:
                raise ValueError(f"smoothing_window must be odd and larger than smoothing_order "
                                 f"({self.smoothing_order}), got {window}; use 0 to turn smoothing off")
            if window > self.horizon:
                raise ValueError(f"smoothing_window ({window}) must not exceed the horizon ({self.horizon})")
        return self

    @property
    def savgol_window(self) -> int:
        """The Savitzky-Golay window the planner applies [steps]; 0 = none (`smoothing_window`)."""
        if self.smoothing_window is not None:
            return self.smoothing_window
        if self.update == "paper":
            return 0
        window = min(DEFAULT_SMOOTHING_WINDOW, self.horizon - (1 - self.horizon % 2))  # odd, within the horizon
        return window if window > self.smoothing_order else 0

    @property
    def noise_memory(self) -> float:
        """The AR(1) memory of the sampling noise from one step to the next (0 = white)."""
        return noise_memory(self.noise_correlation_time, self.dt) if self.sampling == "coloured" else 0.0

    def critic_weights(self, task: str) -> dict[str, float]:
        """The weight of each critic (`CRITICS`) by name in a task kind ('lane' or 'goal'): 0 where it is disabled or
        not run in that kind."""
        return critic_weights(self.critics, task)

    def cost_bundle(self, task: str) -> CostBundle:
        """The kernels' cost input for a task kind: the critic weights and parameters by name, and the goal switch."""
        params = {name: {p: s[p] for p in s if p not in CRITIC_KEYS} for name, s in self.critics.items()}
        return CostBundle.from_weights(self.critic_weights(task), params, self.goal_distance == "geodesic")
