"""Planner configuration: every setting of the GP-MPPI planner, validated (pydantic, frozen).

The same costs and settings apply to every dynamics choice, so the baselines are fair.
"""

from __future__ import annotations

from math import pi
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from gpmppi.mppi.bundles import CRITICS, CostBundle

__all__ = ["PlannerConfig"]


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
    backend: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="Kernels: numba CPU, numba CUDA (grid GP only), or auto (CUDA when numba finds a GPU)"
    )
    samples: int = Field(1024, ge=1, description="Number of sampled control sequences S")
    horizon: int = Field(40, ge=1, description="Horizon N [steps]")
    dt: float = Field(0.1, gt=0, description="Step of the rollouts [s]")
    temperature: float = Field(1.0, gt=0, description="MPPI temperature lambda of the softmax over costs")
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
    # the critics' weights, `w_<critic>` for each name of `CRITICS` (how the defaults were chosen:
    # docs/planner_config.md)
    w_variance: float = Field(
        1.0, ge=0, description="Weight of the GP variance critic, sum of var_v + var_w over the steps [cost / (m/s)^2]"
    )
    w_deviation: float = Field(300.0, ge=0, description="Weight of the lane deviation critic (d / r)^2 per step [cost]")
    w_slip: float = Field(
        0.1, ge=0,
        description="Weight of the slip critic (v_ref - v)^2 + (omega_ref - omega)^2 per step [cost / (m/s)^2]",
    )
    w_lane_exit: float = Field(
        1000.0, ge=0,
        description="Weight of the lane-exit critic: outside the tightened lane at step k costs weight * discount^k "
        "[cost]",
    )
    lane_exit_discount: float = Field(
        0.9, gt=0, le=1, description="Discount per step of the lane-exit critic (dimensionless)"
    )
    w_speed: float = Field(
        2.0, ge=0, description="Weight of the speed critic (v_lane - speed_target)^2 per step [cost / (m/s)^2]"
    )
    speed_along_lane: bool = Field(
        True,
        description="Speed critic on the speed along the lane (v cos of the heading error; the centre line's point "
        "order is the driving direction) instead of the speed magnitude as in the paper",
    )
    w_collision: float = Field(
        1000.0, ge=0, description="Weight of the collision critic: inside an inflated obstacle at a step [cost]"
    )
    goal_distance: Literal["geodesic", "euclidean"] = Field(
        "geodesic",
        description="Distance of the goal critics: the shortest path around the obstacles or the straight line as "
        "in the paper",
    )
    goal_cell: float = Field(0.1, gt=0, description="Cell of the geodesic goal-distance grid [m]")
    w_goal: float = Field(1.0, ge=0, description="Weight of the goal critic: distance to the goal per step [cost / m]")
    w_terminal: float = Field(
        10.0, ge=0, description="Weight of the terminal critic: distance to the goal at the horizon's end [cost / m]"
    )

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
            raise ValueError(f"accel_limits must be positive, got {self.accel_limits}")
        if self.smoothing_window:
            if self.smoothing_window % 2 == 0 or self.smoothing_window <= self.smoothing_order:
                raise ValueError("smoothing_window must be odd and larger than smoothing_order")
            if self.smoothing_window > self.horizon:
                raise ValueError("smoothing_window must not exceed the horizon")
        return self

    def critic_weights(self) -> dict[str, float]:
        """The weight of each critic (`CRITICS`) by name, from the `w_<critic>` fields."""
        return {name: float(getattr(self, f"w_{name}")) for name in CRITICS}

    def cost_bundle(self) -> CostBundle:
        """The kernels' cost input: the critic weights by name, the lane-exit discount and the two switches."""
        return CostBundle.from_weights(self.critic_weights(), self.lane_exit_discount, self.speed_along_lane,
                                       self.goal_distance == "geodesic")
