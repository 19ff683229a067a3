"""One planning cycle: what happens between a state arriving and its command leaving, free of any transport.

The planner service drives a `PlannerCycle` from its Zenoh loop and the closed-loop evaluation drives one from its
simulation, so both run the same checks and the same delay compensation:

- task updates (a task of another kind forgets the warm start; a new lane or goal of the kind being planned for, a
  navigation stack's replanned path, keeps it, so the robot drives on through the swap);
- terrain-weight updates: the table collapse for new weights is done when they arrive (`Planner.prepare`), off
  the state -> command path; weights not refreshed for `weights_stale_after_s` are kept but flagged stale, and
  after `weights_fallback_after_s` replaced by the prior (uniform). Weights equal to the prior are never stale:
  falling back would change nothing;
- state checks: refused when there is no task, when the state is not five finite numbers, older than
  `max_state_age_s` or stamped more than `max_state_future_s` in the future (clock skew); an odometry jump
  (teleport, relocalisation) resets the warm start;
- the start covariance from the state's own (a matrix that is not a covariance falls back to the planner's
  configured `state_std`);
- delay compensation: the plan starts from the state predicted to when its command acts (state age + this
  plan's compute time, estimated by the last one + `actuation_delay_s`);
- the plan itself; a failed or non-finite plan gives no command.

Times: `now` is a monotonic time [s] (arrivals, weight ages), `now_ns` the clock the state stamps are compared
with [ns], as in egress's `Safety`. What happened goes into `events` (each named, with a level and a message) and
`counts`; the caller reports them (the service: heartbeat counters and log).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, Protocol

import numpy as np

from gpmppi.mppi.caution import cautious_task, extra_variance
from gpmppi.mppi.cycle_config import CycleConfig

if TYPE_CHECKING:
    from gpmppi.costmap import Costmap
    from gpmppi.mppi.planner import PlanResult
    from gpmppi.tasks import Task

# "count": counted (the heartbeat's counters), not logged: it may come at every state under load
Level = Literal["reject", "error", "warning", "info", "count"]
# why a state gave no command
Refusal = Literal["no_task", "state_nonfinite", "state_stale", "state_future", "plan_failed", "plan_nonfinite",
                  "costmap_stale"]


class PlannerLike(Protocol):
    def plan(self, state: np.ndarray, task: Task, weights: np.ndarray | None = None,
             state_cov: np.ndarray | None = None, delay_s: float = 0.0) -> PlanResult: ...
    def prepare(self, weights: np.ndarray | None) -> None: ...
    def reset(self) -> None: ...


@dataclass(frozen=True)
class Event:
    """Something the cycle did or refused: `name` is its counter, `level` how the service logs it."""

    name: str
    level: Level
    message: str


@dataclass(frozen=True)
class Planned:
    """A plan to publish: its command is `result.control`, stamped with the state's stamp."""

    result: PlanResult
    stamp_ns: int  # the stamp of the state it was planned from [ns]
    delay_s: float  # how far ahead of the state it planned [s]
    plan_s: float  # how long `plan` took by the cycle's clock [s]
    weights_stale: bool  # the weights it used were stale


def odometry_jump(previous: tuple[int, np.ndarray], stamp_ns: int, x: np.ndarray, config: CycleConfig) -> str | None:
    """Why the step from `previous` (stamp, state) to (`stamp_ns`, `x`) is a jump no motion explains, or None."""
    dt = abs(stamp_ns - previous[0]) / 1e9
    x0 = previous[1]
    distance = float(np.hypot(x[0] - x0[0], x[1] - x0[1]))
    explained = max(abs(x0[3]), abs(x[3])) * dt
    if distance > config.jump_distance_m + explained:
        return f"odometry jumped {distance:.2f} m in {dt:.3f} s (speed explains {explained:.2f} m)"
    yaw = abs(float(np.angle(np.exp(1j * (x[2] - x0[2])))))
    explained = max(abs(x0[4]), abs(x[4])) * dt
    if yaw > config.jump_yaw_rad + explained:
        return f"odometry heading jumped {yaw:.2f} rad in {dt:.3f} s (yaw rate explains {explained:.2f} rad)"
    return None


def plan_is_finite(result: PlanResult) -> bool:
    """Whether a plan's command and nominal trajectory are finite numbers (the rest of a Plan is checked when
    it is published)."""
    return bool(np.all(np.isfinite(result.control)) and np.all(np.isfinite(result.states)))


def weights_in_order(names: Sequence[str], values: Sequence[float], terrains: Sequence[str]) -> np.ndarray:
    """Weights given by terrain name, in the order of `terrains`; ValueError when the names differ."""
    if sorted(names) != sorted(terrains):
        raise ValueError(f"terrain weights for {list(names)} but the model has {list(terrains)}")
    by_name = dict(zip(names, values, strict=True))
    return np.array([by_name[t] for t in terrains], dtype=np.float64)


class PlannerCycle:
    """The planner's cycle over a planner object, free of Zenoh: feed it tasks, weights and states, get plans.

    `clock` times each plan for the next one's delay estimate: the service's monotonic clock; a simulation
    passes its own, under which planning takes no time (its command latency is all in `actuation_delay_s`)."""

    def __init__(
        self, planner: PlannerLike, task: Task | None, config: CycleConfig, n_terrains: int,
        terrains: Sequence[str] | None = None, clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if terrains is not None and len(terrains) != n_terrains:
            raise ValueError(f"{n_terrains} terrains but names {list(terrains)}")
        self.planner = planner
        self.task = task
        self.config = config
        self.terrains = None if terrains is None else list(terrains)
        self.clock = clock
        self.prior = np.full(n_terrains, 1.0 / n_terrains)
        self.weights = self.prior.copy()  # what the next plan uses, in the model's terrain order
        self.weights_time: float | None = None  # arrival of the last valid weights [monotonic s]
        self.weights_stale = False
        self.weights_prior = True
        self.unknown_active = False  # the terrain service says the ground is none of the trained ones
        # ... and by its grip: the free-run channel said so while it lasts (goal tasks are approached slower)
        self.unknown_grip = False
        self.previous: tuple[int, np.ndarray] | None = None  # the last state planned from: (stamp, array)
        self._planned_ns: int | None = None  # the stamp of the last state a plan was made from (its warm start's) [ns]
        self.last_plan_s = 0.0
        self.events: list[Event] = []
        self.counts: dict[str, int] = {}
        self._resume: tuple[np.ndarray, int, float] | None = None  # a predecessor's plan for the first state
        self.costmap: Costmap | None = None  # the grid of goal tasks that come without one (`set_costmap`)
        self.costmap_time: float | None = None  # its arrival [monotonic s] (None: it does not age)
        self._costmap_stale = False

    # ---- reporting
    def _event(self, name: str, level: Level, message: str) -> Event:
        event = Event(name, level, message)
        self.events.append(event)
        self.counts[name] = self.counts.get(name, 0) + 1
        return event

    def drain_events(self) -> list[Event]:
        """What happened since the last call, oldest first."""
        events, self.events = self.events, []
        return events

    # ---- inputs between states
    def swap_planner(self, planner: PlannerLike, terrains: Sequence[str]) -> None:
        """Plan with `planner` (over a model with grounds `terrains`, e.g. one more learned ground) from the next state
        on: called between states, so no plan mixes the two. The warm start carries over (the robot is driving it);
        the weights restart from the prior over the new grounds until the terrain service's next weights, which
        name them."""
        warm = getattr(self.planner, "warm_start", None)
        self.planner = planner
        self.terrains = list(terrains)
        self.prior = np.full(len(self.terrains), 1.0 / len(self.terrains))
        self.weights, self.weights_prior = self.prior.copy(), True
        planner.prepare(self.weights)
        resume = getattr(planner, "resume", None)
        if warm is not None and resume is not None:
            resume(warm, 0)

    def weights_pending(self, now: float) -> None:
        """Weights arrived for a model still loading (`swap_planner` comes next): the terrain estimate is alive, so
        the weights planned with do not age meanwhile (no stale alarm for the second a swap takes)."""
        if self.weights_time is not None and not self.weights_prior:
            self.weights_time, self.weights_stale = now, False

    def resume_from(self, controls: Sequence[Sequence[float]] | np.ndarray, stamp_ns: int, dt: float) -> None:
        """Start from a predecessor's last plan (its control sequence, planned from a state stamped `stamp_ns`)
        instead of the configured initial sequence: at the next state, shifted by the steps of `dt` since, so a
        planner that takes over at speed does not start from zero commands (`Planner.resume`). A plan older than
        its horizon, or a jump at that state, leaves the usual start."""
        self._resume = (np.asarray(controls, dtype=np.float64), int(stamp_ns), float(dt))

    def _apply_resume(self, stamp_ns: int) -> None:
        controls, plan_ns, dt = self._resume  # type: ignore[misc]
        self._resume = None
        steps = max(0, round((stamp_ns - plan_ns) / 1e9 / dt))
        resume = getattr(self.planner, "resume", None)
        if resume is not None and resume(controls, steps):
            self._event("resumed", "info", f"warm start from the predecessor's last plan, shifted {steps} steps "
                        f"({(stamp_ns - plan_ns) / 1e9:.3f} s)")
        else:
            self._event("resume_skipped", "warning", f"the predecessor's last plan ({(stamp_ns - plan_ns) / 1e9:.3f} "
                        "s old) does not fit: starting from the configured initial sequence")

    def _catch_up(self, elapsed_ns: int) -> None:
        """The warm start shifted by the time between the states' stamps, not by one step per plan: after lost
        states (an ingress that took over, a state dropped under load) it would otherwise start that many steps
        behind the robot (`Planner.catch_up`). A state one dt after the last changes nothing."""
        catch_up = getattr(self.planner, "catch_up", None)
        if catch_up is not None and (steps := catch_up(elapsed_ns / 1e9)):
            self._event("warm_start_caught_up", "count", f"warm start shifted {steps} more steps: this state came "
                        f"{elapsed_ns / 1e9:.3f} s after the last one planned from")

    def set_task(self, task: Task) -> None:
        """Plan for `task` from now on. A task of the kind being planned for (a replanned path, a moved goal) keeps
        the warm start: the robot is driving the sequence it holds, and the configured initial one (zero) would brake
        it at every new path of a navigation stack, which replans about once a second. A task of another kind, or
        the first one, starts from the initial sequence. A goal task without a grid of its own plans among the grid
        of `set_costmap`, if one was given."""
        same_kind = self.task is not None and type(task) is type(self.task)
        task = self._with_costmap(task)
        if (grid := getattr(task, "costmap", None)) is not None and grid.clearance(task.goal)[0] < 0:
            x, y = (float(a) for a in task.goal)
            self._event("goal_lethal", "reject", f"goal ({x:.2f}, {y:.2f}) lies in a lethal cell of the costmap: "
                        "refused, planning on for the last task; send a goal in free space")
            return
        self.task = task
        if not same_kind:
            self.planner.reset()

    def set_costmap(self, costmap: Costmap | None, now: float | None = None) -> None:
        """Plan goal tasks among this grid's obstacles from now on (None: none but the task's circles). The warm
        start stays: a new grid is the same task in an updated world. What the plans read of the grid (its distance
        transform, the goal field around it) is built now, between states (`Planner.prepare_task`, when the planner
        has it), not on the next state's path to its command. `now` [monotonic s]: its arrival, from which it ages
        (`max_costmap_age_s`); None: it does not age."""
        self.costmap = costmap
        self.costmap_time = None if costmap is None else now
        self._costmap_stale = False
        if self.task is not None:
            self.task = self._with_costmap(self.task, replace_own=True)
            prepare = getattr(self.planner, "prepare_task", None)
            if prepare is not None and self.previous is not None:
                prepare(self.task, self.previous[1])

    def _with_costmap(self, task: Task, replace_own: bool = False) -> Task:
        return task.with_costmap(self.costmap, replace_own)

    def on_weights(self, weights: Sequence[float], now: float, names: Sequence[str] | None = None,
                   unknown_active: bool = False, unknown_channel: str = "") -> bool:
        """Take new terrain weights (in the model's order, or by `names`); False when refused (the previous stay).
        `unknown_active`: the ground is none of the trained ones (`TerrainWeights.unknown_active`): the plans are
        careful while it lasts (`CautionConfig`); `unknown_channel` (`TerrainWeights.unknown_channel`): `free-run`
        says no trained ground explains its grip, which makes the caution bound a goal task's approach speed.

        The table collapse for them is done now: new weights arrive between states (terrain solves after each
        command), so it stays off the next state's path to its command."""
        try:
            w = np.array(weights, dtype=np.float64).reshape(-1)  # a copy: the caller may reuse its array
            if names is not None:
                if self.terrains is None:
                    raise ValueError("weights by name, but this cycle was not given the model's terrain names")
                if len(names) > len(self.terrains) and set(self.terrains) <= set(names):
                    # grounds learned after this model: the terrain service announces the model that has them
                    # (`ModelUpdate`) before such weights, but the two keys are not ordered, so they may come first.
                    # Not refused; the weights planned with age as usual until the new model is taken.
                    self._event("weights_ahead_of_model", "count", f"terrain weights for {list(names)} before the "
                                f"model that has them; kept the previous weights")
                    return False
                w = weights_in_order(names, w.tolist(), self.terrains)
            self.planner.prepare(w)
        except ValueError as exc:
            self._event("weights_invalid", "reject", f"terrain weights: {exc}; kept the previous weights")
            return False
        if self.weights_stale:
            self._event("weights_back", "info",
                        f"terrain weights arrive again after {now - (self.weights_time or now):.1f} s")
        self.weights = w
        self._set_unknown(unknown_active, unknown_channel)
        self.weights_time, self.weights_stale = now, False
        self.weights_prior = bool(np.allclose(w, self.prior, rtol=0.0, atol=1e-9))
        return True

    def _set_unknown(self, active: bool, channel: str = "") -> None:
        active = bool(active) and self.config.unknown_caution
        # a loss of grip, once seen while the alarm lasts, is kept to its end: the alarm is held across the straights
        # whose runs cannot show grip, where the larger probability may be the one-step channel's
        self.unknown_grip = active and (self.unknown_grip or channel == "free-run")
        if active != self.unknown_active:
            self.unknown_active = active
            if active:
                c = self.config
                goal = "" if c.unknown_goal_speed is None or not self.unknown_grip else (
                    f", goal approached at {c.unknown_goal_speed:g} m/s braking {c.unknown_goal_decel:g} m/s^2")
                self._event("caution_on", "warning", "ground unknown: planning with caution (lane speed x "
                            f"{c.unknown_speed_scale:g}{goal}, extra residual std {list(c.unknown_residual_std)})")
            else:
                self._event("caution_off", "info", "ground known again: planning without the caution")
        if hasattr(self.planner, "extra_variance"):
            self.planner.extra_variance = extra_variance(self.config) if active else (0.0, 0.0)

    def tick(self, now: float) -> None:
        """Age the terrain weights: flag them stale, then fall back to the prior."""
        if self.weights_time is None or self.weights_prior:
            return
        silent = now - self.weights_time
        if not self.weights_stale and silent > self.config.weights_stale_after_s:
            self.weights_stale = True
            self._event("weights_stale", "error",
                        f"no terrain weights for {silent:.1f} s: planning on the last ones (stale)")
        if silent > self.config.weights_fallback_after_s:
            self.weights_prior = True
            self.weights = self.prior.copy()
            self.planner.prepare(self.weights)
            self._event("weights_fallback", "error",
                        f"no terrain weights for {silent:.1f} s: planning on the prior (uniform weights)")

    def _costmap_age(self, now: float) -> float | None:
        """The age [s] of the grid the task plans among when it is too old (`max_costmap_age_s`), else None."""
        limit, grid = self.config.max_costmap_age_s, getattr(self.task, "costmap", None)
        if limit is None or self.costmap_time is None or grid is None or grid is not self.costmap:
            return None
        age = now - self.costmap_time
        return age if age > limit else None

    # ---- a state
    def _refuse(self, reason: Refusal, level: Level, message: str) -> Event:
        return self._event(reason, level, message)

    def _start_covariance(self, covariance: Sequence[float] | np.ndarray | None) -> np.ndarray | None:
        if covariance is None:
            return None
        cov = np.asarray(covariance, dtype=np.float64)
        if cov.size == 25:
            cov = cov.reshape(5, 5)
            if np.all(np.isfinite(cov)) and not np.any(np.diag(cov) < 0) and np.allclose(cov, cov.T):
                return cov
        self._event("state_covariance_invalid", "reject",
                    "state covariance is not a covariance (negative variance or asymmetric): planned with the "
                    "configured state_std instead")
        return None

    def on_state(
        self, state: Sequence[float] | np.ndarray, stamp_ns: int, now: float, now_ns: int,
        covariance: Sequence[float] | np.ndarray | None = None,
    ) -> Planned | Event:
        """Plan from `state` (stamped `stamp_ns`, with its 5x5 or flat covariance, if any); the plan, or the
        refusal (an `Event` whose name says why; there is no command then, and egress's watchdog stops the
        robot if it persists)."""
        c = self.config
        self.tick(now)
        if self.task is None:
            return self._refuse("no_task", "reject", "no task yet: not planning")
        if (age := self._costmap_age(now)) is not None:
            return self._refuse("costmap_stale", "error", f"the costmap is {age:.2f} s old (limit "
                                f"{self.config.max_costmap_age_s} s): not planning among it; waiting for a new grid")
        x = np.asarray(state, dtype=np.float64).reshape(-1)
        if x.shape != (5,) or not np.all(np.isfinite(x)):
            return self._refuse("state_nonfinite", "reject",
                                f"state {x.tolist()} is not five finite numbers: not planning")
        age_s = (now_ns - stamp_ns) / 1e9
        if age_s > c.max_state_age_s:
            return self._refuse("state_stale", "reject",
                                f"state is {age_s:.3f} s old (limit {c.max_state_age_s} s): not planning")
        if -age_s > c.max_state_future_s:
            return self._refuse("state_future", "reject",
                                f"state stamped {-age_s:.3f} s in the future (limit {c.max_state_future_s} s): not "
                                "planning; the state source's clock is ahead of this host's")
        jumped = False
        if self.previous is not None and (jump := odometry_jump(self.previous, stamp_ns, x, c)):
            # the warm start was planned for the old pose: from the new one it is a wrong guess
            self._event("odom_jump", "warning", f"{jump}: warm start reset")
            self.planner.reset()
            self._resume = None
            jumped = True
        if self._planned_ns is not None and not jumped and self._resume is None:
            self._catch_up(stamp_ns - self._planned_ns)
        self.previous = (stamp_ns, x)
        if self._resume is not None:
            self._apply_resume(stamp_ns)
        cov = self._start_covariance(covariance)
        # the command acts once this plan is computed (about as long as the last one) and has reached the base
        delay_s = max(0.0, age_s) + self.last_plan_s + c.actuation_delay_s if c.compensate_delay else 0.0
        try:
            t_plan = self.clock()
            task = cautious_task(self.task, self.config, self.unknown_grip) if self.unknown_active else self.task
            result = self.planner.plan(x, task, self.weights, state_cov=cov, delay_s=delay_s)
            self.last_plan_s = self.clock() - t_plan
            self._planned_ns = stamp_ns
        except (ValueError, FloatingPointError) as exc:
            return self._refuse("plan_failed", "error", f"planning failed: {exc}")
        if not plan_is_finite(result):
            # a state far outside what the model knows (e.g. v = -5 m/s with omega = 20 rad/s) can make the
            # rollouts diverge: such a plan is no plan, so no command
            return self._refuse("plan_nonfinite", "error",
                                f"planning from {np.round(x, 3).tolist()} gave non-finite states: no command")
        return Planned(result, stamp_ns, delay_s, self.last_plan_s, self.weights_stale)
