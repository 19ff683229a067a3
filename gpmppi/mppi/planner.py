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

import numpy as np

from gpmppi.gp.model_file import GPModel
from gpmppi.mppi import backends, compile_ahead
from gpmppi.mppi.bundles import ModelBundle, Outputs, SamplingBundle, TaskBundle
from gpmppi.mppi.config import PlannerConfig
from gpmppi.mppi.costs import ChanceQuantiles
from gpmppi.mppi.critics.registry import layout
from gpmppi.mppi.dynamics import predict_ahead, propagate
from gpmppi.mppi.savgol import savgol_matrix
from gpmppi.mppi.task_kinds import TaskKind, kind_class_for, registered_kinds
from gpmppi.mppi.temperature import temperature_for_effective_samples
from gpmppi.mppi.terrain_table import TerrainTable
from gpmppi.tasks import Task

__all__ = ["PlanResult", "Planner", "PlannerConfig"]

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
    # each critic's share of `cost` (`CRITICS` names); they sum to `cost`
    critic_costs: dict[str, float] = field(default_factory=dict)
    # Kish's effective sample size of the update, 1 / sum(w_s^2) over the normalised softmax weights: 1 when one
    # rollout decides the update, `samples` when all weigh the same; 0 when every rollout's cost was infinite
    effective_samples: float = 0.0
    temperature: float = 0.0  # the softmax temperature of this update (update=smooth: chosen for the sample size)


class Planner:
    """GP-MPPI over a `GPModel`; `plan` is one receding-horizon iteration (warm-started).

    What depends on the terrain weights (the collapsed GP table, the noise, the EDD5 terrain) is its `terrain`
    (`TerrainTable`); what depends on the task's kind (checks, bounds, the kernels' task input, the critics) is that
    kind's (`task_kinds`); the planner keeps the MPPI iteration and its warm start.
    """

    def __init__(self, config: PlannerConfig, model: GPModel) -> None:
        self.config = config
        self.model = model
        c = config
        exact_gp = c.dynamics == "gp" and c.gp_mode == "exact"
        if exact_gp and c.backend == "cuda":
            raise ValueError("backend='cuda' evaluates the GP by grid only; use gp_mode='grid' or backend='cpu'")
        self.backend = "cpu" if exact_gp else backends.resolve(c.backend)
        self.device = backends.device_inputs(self.backend)  # the kernel's inputs kept on the GPU between plans
        self.terrain = TerrainTable(c, model, self.backend)
        self._quant = ChanceQuantiles.for_probability(c.p_x)
        # one of each registered task kind, by task type (a kind registered later: made on its first task)
        self._kinds = {t: kind(c, self._quant) for t, kind in registered_kinds().items()}
        self._u_lo = np.array([c.v_limits[0], c.omega_limits[0]])
        self._u_hi = np.array([c.v_limits[1], c.omega_limits[1]])
        self._default_state_cov = np.diag(np.square(np.asarray(c.state_std, dtype=np.float64)))
        # the largest change of the command sent from one plan to the next [m/s, rad/s] (`rng.sampled_command`)
        limits = c.accel_limits
        self._rate_step = np.full(2, np.inf) if limits is None else np.asarray(limits, dtype=np.float64) * c.dt
        self._smoother = savgol_matrix(c.horizon, c.savgol_window, c.smoothing_order) if c.savgol_window else None
        self._may_compile_ahead = self.backend == "cpu"  # until the first plan (`compile_ahead`)
        # per-step residual variance [(m/s)^2, (rad/s)^2] the chance constraints add beyond the GP's: the caution on
        # unknown ground (gpmppi/mppi/caution.py; `PlannerCycle` sets it), zero otherwise
        self.extra_variance = (0.0, 0.0)
        self.reset()

    def reset(self) -> None:
        """Forget the warm start, the last control and the iteration counter (plans repeat from here)."""
        c = self.config
        self._nominal = np.tile(np.clip(np.array(c.initial_control, dtype=np.float64), self._u_lo, self._u_hi),
                                (c.horizon, 1))
        self._last_control: np.ndarray | None = None
        self._iteration = 0
        for kind in self._kinds.values():
            kind.reset()

    def warm_up(self, state: np.ndarray, task: Task) -> None:
        """Plan as a live service does in its first seconds, so that numba has compiled or loaded every kernel of
        that path before it goes live; then `reset`. Once on the uniform weights with a command latency (the delay
        predictor), then on new weights collapsed ahead (`prepare`: `lazy_collapse.collapse_slabs_at`) and once more
        when they hold (the rest of the table, `collapse_into`). Without the last two a fresh install compiled them at
        the first weights from the terrain service, between two commands: 1.1 s and 0.4 s on 2 cores."""
        x = np.asarray(state, dtype=np.float64)
        self.plan(x, task, delay_s=0.01)
        weights = np.arange(1.0, len(self.model.terrains) + 1.0)
        weights /= weights.sum()  # any weights but the uniform start's
        for _ in range(2):
            self.prepare(weights)
            self.plan(x, task, weights, delay_s=0.01)
        self.reset()

    @property
    def warm_start(self) -> np.ndarray:
        """(N, 2) the control sequence the next plan starts from (a copy): what a successor planner resumes."""
        return self._nominal.copy()

    def resume(self, controls: np.ndarray, steps: int) -> bool:
        """Warm-start from another planner's sequence (a predecessor's last plan, `controls` (N, 2) from its
        state on), `steps` dt-steps later: its controls from `steps` on, the last one held for the rest. The
        command in effect stays unknown (the state's own velocities, as after `reset`). False, and nothing
        changed, when the sequence does not fit this planner or has run out (`steps` >= its length)."""
        c = self.config
        u = np.asarray(controls, dtype=np.float64)
        if u.ndim != 2 or u.shape[1] != 2 or u.shape[0] == 0 or not np.all(np.isfinite(u)):
            return False
        if not 0 <= steps < u.shape[0]:
            return False
        u = u[steps:][: c.horizon]
        u = np.concatenate([u, np.repeat(u[-1:], c.horizon - u.shape[0], axis=0)], axis=0)
        self._nominal = np.clip(u, self._u_lo, self._u_hi)
        self._last_control = None
        return True

    def catch_up(self, elapsed_s: float) -> int:
        """Align the warm start with a state that came `elapsed_s` after the one the last plan was made from.

        Each plan leaves its sequence shifted by one step for the next, which is right when the next state comes one
        `dt` later. When states were lost (an ingress that took over, a state dropped under load, a planner busy past
        one), more steps have passed: the robot has driven those commands already, so they are dropped too (the last
        held for the rest, as the shift does). Returns the steps dropped beyond the one: 0 for a state about one dt
        later (the rounding's half-step tolerance absorbs stamp jitter), or an earlier one."""
        c = self.config
        if not np.isfinite(elapsed_s):
            return 0
        extra = min(int(round(elapsed_s / c.dt)) - 1, c.horizon)
        if extra < 1:
            return 0
        u = self._nominal
        self._nominal = np.concatenate([u[extra:], np.repeat(u[-1:], extra, axis=0)], axis=0)
        return extra

    def kind(self, task: Task) -> TaskKind:
        """This planner's kind of `task` (`task_kinds`); a ValueError for a task of no registered kind."""
        kind = self._kinds.get(type(task))
        if kind is None:
            kind = self._kinds[type(task)] = kind_class_for(task)(self.config, self._quant)
        return kind

    def prepare_task(self, task: Task, state: np.ndarray) -> None:
        """Build what `task`'s plans read once per task (its kind's `prepare`: a grid's distance transform, the goal
        field around its obstacles) now, from `state`, rather than in the next `plan`. Like `prepare`: between
        plans, from the thread that plans."""
        self.kind(task).prepare(task, np.asarray(state, dtype=np.float64).reshape(-1)[:5])

    # ---------------------------------------------------------------- inputs
    def _check_inputs(self, state: np.ndarray, task: Task, weights: np.ndarray | None) -> tuple:
        x = np.asarray(state, dtype=np.float64).reshape(-1)
        if x.shape != (5,):
            raise ValueError(f"state must be [X, Y, theta, v, omega] (5 numbers), got shape {np.shape(state)}")
        if not np.all(np.isfinite(x)):
            raise ValueError(f"state must be finite, got {x.tolist()}; drop this state and wait for the next one")
        kind = self.kind(task)
        w = self.terrain.check_weights(weights)
        kind.check(task)
        return np.ascontiguousarray(x), w, kind

    def prepare(self, weights: np.ndarray | None) -> None:
        """Get ready to plan with these terrain weights: collapse the GP table now rather than in the next `plan`.

        A service calls this when new weights arrive, between states, which takes the collapse off the state ->
        command path. Collapsed lazily (the default), it collapses every slab of the box of cells the plans of the last
        few weights read (`lazy_collapse`: the next plan's lookups inside it check nothing) and of the cells they read
        outside it (on CUDA only the nominal's: the device collapses its own table in the plan, ~0.1 ms); collapsed
        whole, all of it (28.5 MB of per-terrain table for the shipped model).
        Not while a plan runs (the lazily collapsed table is rewritten in place): call both from one thread.
        """
        self.terrain.set_weights(self.terrain.check_weights(weights), ahead=True)

    def _noise_var(self, model: ModelBundle) -> tuple[float, float]:
        """The step variance the covariance propagation adds beyond what the kernels' GP gives (the exact GP's
        likelihood noise, the caution's extra variance)."""
        nv, nw = self.terrain.exact_noise_var(model.terrain_w)
        return nv + self.extra_variance[0], nw + self.extra_variance[1]

    def _propagate(self, x: np.ndarray, controls: np.ndarray, model: ModelBundle, cov0: np.ndarray) -> tuple:
        return propagate(model.args(), x, controls, self.config.dt, *self._noise_var(model), cov0)

    def _predict_ahead(
        self, x: np.ndarray, cov0: np.ndarray, delay_s: float, model: ModelBundle
    ) -> tuple[np.ndarray, np.ndarray]:
        """The state (and covariance) when this plan's command takes effect, `delay_s` after the measurement.

        A command published late does not act on the measured state but on the one the robot has reached by
        then, under the command still in effect: the last one this planner returned (since a reset: the
        state's own velocities, held). Without it the loop tracks worse the longer the latency: with 150 ms,
        circle RMSE 68.0 mm against 36.0 with it (README, "Delay compensation").
        """
        c = self.config
        if not (np.isfinite(delay_s) and 0.0 <= delay_s <= c.horizon * c.dt):
            raise ValueError(
                f"delay_s must be between 0 and the horizon ({c.horizon * c.dt:.2f} s), got {delay_s}; "
                "a state that old is stale: drop it"
            )
        held = self._command_in_effect(x)
        return predict_ahead(model.args(), x, cov0, np.ascontiguousarray(held, dtype=np.float64), float(delay_s),
                             c.dt, *self._noise_var(model))

    def _command_in_effect(self, x: np.ndarray) -> np.ndarray:
        """The command the base is under at state `x`: the last one this planner returned (since a reset: the
        state's own velocities, held, within the limits)."""
        return self._last_control if self._last_control is not None else np.clip(x[3:5], self._u_lo, self._u_hi)

    def _state_covariance(self, state_cov: np.ndarray | None) -> np.ndarray:
        if state_cov is None:
            return self._default_state_cov
        cov = np.asarray(state_cov, dtype=np.float64)
        if cov.shape != (5, 5) or not np.all(np.isfinite(cov)):
            raise ValueError(
                f"state_cov must be a finite 5x5 covariance of [x, y, yaw, v, omega], got shape {cov.shape}"
            )
        cov = 0.5 * (cov + cov.T)
        if np.any(np.diag(cov) < 0):
            raise ValueError("state_cov has a negative variance on its diagonal")
        return cov

    def _bounds(self, kind: TaskKind, task: Task, states: np.ndarray, covs: np.ndarray) -> tuple[np.ndarray, int]:
        """The task kind's bounds (tightened half-widths (N+1,), effective obstacle radii (N+1, K)) and clamp count;
        untightened (zero covariances) with `tightening` off."""
        if not self.config.tightening:
            covs = np.zeros_like(covs)
        return kind.bounds(task, states, covs)

    # ---------------------------------------------------------------- plan
    def plan(
        self, state: np.ndarray, task: Task, weights: np.ndarray | None = None,
        state_cov: np.ndarray | None = None, delay_s: float = 0.0,
    ) -> PlanResult:
        """One MPPI iteration from `state` for `task` with terrain `weights` (None = uniform).

        `state_cov` (5, 5) is the state estimate's covariance (None = diag(`state_std`)^2). `delay_s` is the
        time from the state's measurement until this plan's command takes effect on the base; the plan starts
        from the state predicted that far ahead (`predict_ahead`).
        """
        c = self.config
        t_start = time.perf_counter()
        x, w, kind = self._check_inputs(state, task, weights)
        cov0 = self._state_covariance(state_cov)
        t_collapse = time.perf_counter()
        model = self.terrain.set_weights(w)
        collapse_ms = (time.perf_counter() - t_collapse) * 1e3
        self.terrain.planned()
        ahead = self._start_compile_ahead(x, kind, model) if self._may_compile_ahead else None
        if delay_s != 0.0:
            x, cov0 = self._predict_ahead(x, cov0, delay_s, model)
        t0 = time.perf_counter()
        nominal = self._nominal
        prev_states, prev_covs, _ = self._propagate(x, nominal, model, cov0)
        bounds, clamped_before = self._bounds(kind, task, prev_states, prev_covs)
        t1 = time.perf_counter()

        task_bundle = kind.task_bundle(task, bounds, x)
        n_xy = min(c.sample_output, c.samples)
        u_hi = self._task_u_hi(kind, task, x)
        sampling = self._sampling(x, nominal, kind.noise_std, u_hi)
        cost = kind.cost
        if ahead is not None:  # the per-critic scorer compiled here while the child compiles the rollout kernel
            backends.critic_costs(model, task_bundle, sampling, cost)
            ahead.wait()
        eps, costs, xy = backends.rollouts(self.backend, model, task_bundle, sampling, cost, c.samples, n_xy,
                                           self.device)
        # exact GP: the kernels' variances are latent; the likelihood noise adds the same to every rollout's cost
        # (the update is unchanged), added here so that costs are those of the predictive variance in every mode,
        # for each critic that declares it reads the variances (`Critic.noise_cost`)
        noise_costs = layout().noise_costs(cost.weights, c.horizon, *self.terrain.exact_noise_var(w))
        costs = costs + sum(noise_costs.values())
        t2 = time.perf_counter()

        temperature = self._temperature(costs)
        new_u, sample_w = backends.softmax_update(nominal, eps, costs, temperature)
        effective_samples = backends.effective_sample_size(sample_w)
        flags: dict[str, int] = {"all_costs_infinite": int(not np.any(np.isfinite(costs)))}
        new_u = self._shape_sequence(new_u, x, u_hi)
        t3 = time.perf_counter()

        states, covs, _ = self._propagate(x, new_u, model, cov0)
        out_bounds, clamped_after = self._bounds(kind, task, states, covs)
        nominal_sampling = self._sampling(x, new_u, np.zeros(2), u_hi)
        # the nominal sequence scored once: each critic's share, whose sum is its cost (the kernels add the same
        # terms step by step; tests/test_critics.py compares the sum with the kernel's cost of this sequence)
        critic_costs = backends.critic_costs(model, task_bundle, nominal_sampling, cost)
        for name, extra in noise_costs.items():
            critic_costs[name] += extra
        nominal_cost = sum(critic_costs.values())
        if not np.isfinite(nominal_cost):
            nominal_cost = np.inf  # as the kernels score a rollout that left the finite
        t4 = time.perf_counter()

        control = new_u[0].copy()
        if not np.all(np.isfinite(new_u)):
            # never hand out a non-finite command: stop, and start the sequence afresh
            flags["nonfinite_fallback"] = 1
            new_u = np.tile(np.clip(np.zeros(2), self._u_lo, self._u_hi), (c.horizon, 1))
            control = new_u[0].copy()
            states = np.repeat(x[None, :], c.horizon + 1, axis=0)
            covs = np.zeros_like(covs)
            out_bounds, clamped_after = self._bounds(kind, task, states, covs)
        else:
            flags["nonfinite_fallback"] = 0
        key = kind.clamp_flag
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
            cost=float(nominal_cost),
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
            critic_costs=critic_costs,
            effective_samples=effective_samples,
            temperature=temperature,
        )

    def _start_compile_ahead(
        self, x: np.ndarray, kind: TaskKind, model: ModelBundle
    ) -> compile_ahead.CompileAhead | None:
        """On the first plan: compile the rollout kernel in a second process when it is not cached
        (`compile_ahead.start` decides), while this one compiles the rest.

        The child gets this plan's model, sampling, cost and outputs and, for the task, an empty one
        (`TaskBundle.for_types`): every task bundle has the same types, so the kernel it compiles is the one this
        task needs, and the child starts at once instead of after this task's bounds and lane lookup (compiled on
        a cold cache: ~5 s)."""
        self._may_compile_ahead = False
        c = self.config
        out = Outputs.allocate(c.samples, c.horizon, min(c.sample_output, c.samples))
        args = (model.args(), TaskBundle.for_types(c.horizon).args(),
                self._sampling(x, self._nominal, kind.noise_std).args(), kind.cost.args(), out.args())
        return compile_ahead.start(args)

    def _task_u_hi(self, kind: TaskKind, task: Task, x: np.ndarray) -> np.ndarray:
        """The upper control limits of this task's plans from `x`: the planner's, the speed bounded by the task's
        own there (`TaskKind.speed_limit`; never below the lower limit)."""
        cap = kind.speed_limit(task, x)
        if cap is None or cap >= self._u_hi[0]:
            return self._u_hi
        return np.array([max(float(cap), self._u_lo[0]), self._u_hi[1]])

    def _sampling(self, x: np.ndarray, nominal: np.ndarray, noise_std: np.ndarray,
                  u_hi: np.ndarray | None = None) -> SamplingBundle:
        c = self.config
        u_hi = self._u_hi if u_hi is None else u_hi
        return SamplingBundle(x0=x, nominal=nominal, noise_std=noise_std, u_lo=self._u_lo, u_hi=u_hi, dt=c.dt,
                              seed=c.seed, iteration=self._iteration, noise_memory=c.noise_memory,
                              u_prev=np.ascontiguousarray(self._command_in_effect(x), dtype=np.float64),
                              rate_step=self._rate_step)

    def _temperature(self, costs: np.ndarray) -> float:
        """This update's softmax temperature: the fixed one (update=paper) or the one that gives the update
        `effective_sample_fraction` of the samples as its effective sample size (update=smooth)."""
        c = self.config
        if c.update == "paper":
            return c.temperature
        return temperature_for_effective_samples(costs, c.effective_sample_fraction * c.samples, c.temperature)

    def _shape_sequence(self, u: np.ndarray, x: np.ndarray, u_hi: np.ndarray) -> np.ndarray:
        """Optional smoothing, then the first command within the rate limits of the command in effect, then the
        control limits.

        Every sample's first command, and so the update's, keeps the rate limits already; the smoothing can move it a
        little, and this puts it back, as the kernels clip a sampled first command (`rng.sampled_command`)."""
        if self._smoother is not None:
            u = self._smoother @ u
        if self.config.accel_limits is not None:
            prev = self._command_in_effect(x)
            u = u.copy()
            u[0] = np.clip(u[0], prev - self._rate_step, prev + self._rate_step)
        return np.ascontiguousarray(np.clip(u, self._u_lo, u_hi))
