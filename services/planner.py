"""planner: GP-MPPI on each new state (or at a fixed rate) with the newest terrain weights and task.

Publishes `cmd` (stamped with the state's stamp, so stamp -> publish is the control latency) and `plan`
(nominal trajectory, position covariances, tightened bounds, a subset of rollouts, timings). The task is the
configured scenario's, re-published once a second on `task`; a Task from another publisher replaces it.

Under faults (docs/safety.md): stale, future-stamped (clock skew) and non-finite states are refused and counted by
name in the heartbeat; silent terrain weights are kept but flagged (`Plan.weights_stale`, heartbeat flag
`weights_stale`, status degraded) and after `weights_fallback_after_s` replaced by the prior (uniform, what the
terrain service itself publishes first); an odometry jump (teleport, relocalisation) resets the warm start.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import Field, ValidationError, model_validator

from gpmppi.mppi.config import PlannerConfig  # not the planner module: run() imports it alongside the model load
from schemas import Command, DecodeError, Plan, State, TerrainWeights, decode
from services.convert import state_to_array, task_from_message, task_to_message
from services.node import Node, NodeSettings, TypedSubscription
from services.scheduling import process_age_s

if TYPE_CHECKING:
    import zenoh

    from gpmppi.gp.model_file import GPModel
    from gpmppi.mppi.planner import PlanResult
    from gpmppi.scenarios import Scenario
    from gpmppi.tasks import GoalTask, LaneTask


class Settings(NodeSettings):
    service: str = Field("planner", description="service name")
    planner: PlannerConfig = Field(default_factory=PlannerConfig, description="GP-MPPI settings")
    scenario: str = Field(
        "circle", description="task: 'circle', 'square', 'paper_obstacles', or a lane_*.yaml / scene_*.yaml file"
    )
    model_file: str | None = Field(None, description="GP model file (None: the shipped model)")
    trigger: Literal["state", "rate"] = Field("state", description="plan on each new state, or at rate_hz")
    rate_hz: float = Field(10.0, gt=0, description="planning rate when trigger == 'rate' [Hz]")
    max_state_age_s: float = Field(0.5, gt=0, description="do not plan from a state older than this [s]")
    max_state_future_s: float = Field(
        0.2, ge=0, description="do not plan from a state stamped further than this in the future: the clock skew "
        "tolerated between the state's source and this host [s]"
    )
    weights_stale_after_s: float = Field(
        1.0, gt=0, description="terrain weights not refreshed for this long are flagged stale (kept, Plan."
        "weights_stale, heartbeat flag weights_stale, status degraded) [s]"
    )
    weights_fallback_after_s: float = Field(
        5.0, gt=0, description="terrain weights not refreshed for this long are replaced by the prior (uniform) [s]"
    )
    jump_distance_m: float = Field(
        0.5, gt=0, description="an odometry jump: consecutive states further apart than this plus what their speed "
        "explains over their stamp gap; resets the warm start [m]"
    )
    jump_yaw_rad: float = Field(
        0.5, gt=0, description="an odometry jump in yaw: consecutive headings further apart than this plus what "
        "their yaw rate explains [rad]"
    )
    compensate_delay: bool = Field(
        True, description="plan from the state predicted to when the command takes effect (state age + compute + "
        "actuation_delay_s), not from the measured one; the age is this host's clock minus the state's stamp, so "
        "the two clocks must agree (one host, or synchronised clocks): turn it off otherwise"
    )
    actuation_delay_s: float = Field(
        0.005, ge=0, le=0.5, description="from publishing `cmd` to the base applying it (egress hop, base tick) [s]"
    )
    plan_samples: int = Field(16, ge=0, description="rollouts (XY) included in each Plan message")
    plan_every: int = Field(1, ge=1, description="publish a Plan every n-th cycle (cmd every cycle)")
    task_period_s: float = Field(1.0, gt=0, description="re-publish the task this often [s]")

    @model_validator(mode="after")
    def _fallback_after_stale(self) -> Settings:
        if self.weights_fallback_after_s < self.weights_stale_after_s:
            raise ValueError(
                f"weights_fallback_after_s {self.weights_fallback_after_s} is shorter than weights_stale_after_s "
                f"{self.weights_stale_after_s}: weights are flagged stale before they are replaced by the prior"
            )
        return self


class StateSubscription(TypedSubscription[State]):
    """The state subscription, naming in the heartbeat why a payload was refused (non-finite numbers apart from
    other junk): a non-finite number never reaches the planner, it is stopped at decoding."""

    def _decode(self, sample: zenoh.Sample) -> State | None:
        counters = self.node.counters
        with counters.lock:
            counters.received += 1
        try:
            msg = decode(State, sample.payload.to_bytes(), self.node.settings.max_payload_bytes)
        except DecodeError as exc:
            cause = exc.__cause__
            nonfinite = isinstance(cause, ValidationError) and any(e["type"] == "finite_number" for e in cause.errors())
            counters.count("state_nonfinite" if nonfinite else "state_invalid")
            self.node.reject(f"{sample.key_expr}: {exc}")
            return None
        self.last = msg
        return msg


def odometry_jump(previous: tuple[int, np.ndarray], stamp_ns: int, x: np.ndarray, settings: Settings) -> str | None:
    """Why the step from `previous` (stamp, state) to (`stamp_ns`, `x`) is a jump no motion explains, or None."""
    dt = abs(stamp_ns - previous[0]) / 1e9
    x0 = previous[1]
    distance = float(np.hypot(x[0] - x0[0], x[1] - x0[1]))
    explained = max(abs(x0[3]), abs(x[3])) * dt
    if distance > settings.jump_distance_m + explained:
        return f"odometry jumped {distance:.2f} m in {dt:.3f} s (speed explains {explained:.2f} m)"
    yaw = abs(float(np.angle(np.exp(1j * (x[2] - x0[2])))))
    explained = max(abs(x0[4]), abs(x[4])) * dt
    if yaw > settings.jump_yaw_rad + explained:
        return f"odometry heading jumped {yaw:.2f} rad in {dt:.3f} s (yaw rate explains {explained:.2f} rad)"
    return None


def load_scenario(name: str) -> Scenario:
    from gpmppi import scenarios

    if name == "paper_obstacles":
        return scenarios.paper_obstacle_scene()
    if name in ("circle", "square"):
        return scenarios.lane_scenario(name)
    path = Path(name)
    if not path.is_file():
        raise FileNotFoundError(f"scenario {name!r}: not 'circle', 'square', 'paper_obstacles' nor an existing file")
    try:
        return scenarios.load_lane(path)
    except ValueError:
        return scenarios.load_scene(path)


def load_model(model_file: str | None) -> GPModel:
    from gpmppi.gp.model_file import GPModel, load_default_model

    return load_default_model() if model_file is None else GPModel.load(model_file)


def plan_is_finite(result: PlanResult) -> bool:
    """Whether a plan's command and nominal trajectory are finite numbers (the rest of a Plan is checked when
    it is published)."""
    return bool(np.all(np.isfinite(result.control)) and np.all(np.isfinite(result.states)))


def plan_message(
    result: PlanResult, stamp_ns: int, task: LaneTask | GoalTask, n_samples: int,
    extra_timings_ms: dict[str, float] | None = None, weights_stale: bool = False,
) -> Plan:
    from gpmppi.tasks import GoalTask

    covs = np.asarray(result.covariances)
    cov_xy = np.stack([covs[:, 0, 0], covs[:, 0, 1], covs[:, 1, 1]], axis=1)
    tightened = np.asarray(result.tightened, dtype=np.float64)
    if isinstance(task, GoalTask) and tightened.ndim == 2:
        # per step: the largest inflation of any obstacle radius
        radii = task.obstacles[:, 2] if task.obstacles.shape[0] else np.zeros(0)
        tightened = (tightened - radii[None, :]).max(axis=1) if radii.size else np.zeros(tightened.shape[0])
    # rollouts are for the viewer: 1 mm is plenty, and short numbers make the bulk of the message (3/4 of its
    # bytes at full precision) cheaper to encode, send, record and decode
    samples = np.round(np.asarray(result.sample_states, dtype=np.float64)[:n_samples], 3)
    command = Command(v_ref=float(result.control[0]), omega_ref=float(result.control[1]))
    command.header.stamp_ns = stamp_ns
    # built without validation: the publisher validates what it sends (finite numbers, shapes) exactly once
    plan = Plan.model_construct(
        command=command,
        controls=np.asarray(result.controls, dtype=np.float64).tolist(),
        states=np.asarray(result.states, dtype=np.float64).tolist(),
        cov_xy=cov_xy.tolist(),
        tightened=tightened.reshape(-1).tolist(),
        samples=samples.tolist(),
        sample_costs=np.asarray(result.sample_costs, dtype=np.float64)[:n_samples].tolist(),
        terrain_weights=np.asarray(result.weights, dtype=np.float64).tolist(),
        weights_stale=weights_stale,
        timings_ms={k: float(v) for k, v in {**result.timings_ms, **(extra_timings_ms or {})}.items()},
    )
    plan.header.stamp_ns = stamp_ns
    return plan


def run(settings: Settings) -> int:
    import gpmppi.gp.model_file  # noqa: F401 - imported here, not concurrently by both threads below

    # a (re)started planner keeps the robot waiting (egress sends zeros) until its first command: where the start
    # spends its time is logged with that command
    startup = {"imports_s": process_age_s()}
    t = time.monotonic()
    # the model file (0.2-0.6 s to read and decode; zlib and numpy release the GIL) loads on a second thread while
    # this one imports the rest of the planner (the kernels' modules) and builds the scenario
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="model-load") as pool:
        loading = pool.submit(load_model, settings.model_file)
        from gpmppi.mppi.planner import Planner

        scenario = load_scenario(settings.scenario)
        model = loading.result()
    task = scenario.task
    startup["planner_import_and_model_s"] = time.monotonic() - t
    weights: np.ndarray | None = None
    with Node(settings) as node:
        # subscribed before the warm-up: the newest state is waiting when it is done (no wait for the next one);
        # the heartbeat, which tells the launcher the planner is up, starts with the loop
        state_sub = StateSubscription(node, node.key("state"), State, newest_only=True, capacity=1024)
        weights_sub = node.subscribe("terrain_weights")
        task_sub = node.subscribe("task", remote_only=True)  # our own re-publications must not loop back
        cmd_pub = node.publisher("cmd")
        plan_pub = node.publisher("plan")
        task_pub = node.publisher("task")
        t = time.monotonic()
        planner = Planner(settings.planner, model)
        # compile / load the numba cache before going live
        planner.plan(np.asarray(scenario.start, dtype=np.float64), task, delay_s=0.01)  # delay: its predictor too
        planner.reset()
        startup["warmup_s"] = time.monotonic() - t
        t = time.monotonic()
        next_task = 0.0
        next_rate_tick = time.monotonic()
        latest: State | None = None
        fresh = False
        previous: tuple[int, np.ndarray] | None = None  # the last state planned from: (stamp, array)
        terrain = TerrainWatch(node, settings)
        cycle = 0
        last_plan_s = 0.0
        while node.ok():
            now = time.monotonic()
            if (new_task := task_sub.take()) is not None:
                try:
                    task = task_from_message(new_task)
                    planner.reset()
                    node.log.info("new task: %s", new_task.kind)
                except ValueError as exc:
                    node.reject(f"task: {exc}")
            w = weights_sub.take()
            if w is not None and (new_weights := _weights_in_model_order(node, w, model)) is not None:
                try:
                    # new weights arrive between states (terrain solves after each command): the table collapse
                    # for them is done now, not on the next state's path to its command
                    planner.prepare(new_weights)
                    weights = new_weights
                    terrain.refreshed(now, new_weights)
                except ValueError as exc:
                    node.reject(f"terrain weights: {exc}; kept the previous weights")
            if terrain.check(now) and weights is not None:
                weights = None  # the prior
                planner.prepare(weights)
            if (s := state_sub.take()) is not None:
                latest, fresh = s, True
            due = fresh if settings.trigger == "state" else now >= next_rate_tick
            if not due or latest is None:
                if now >= next_task:
                    # only here, between cycles: never on a state's path to its command (encoding the lane's
                    # polyline takes milliseconds; a cycle with it on the path measured 22.9 ms, the median 5)
                    next_task = now + settings.task_period_s
                    task_pub.put(task_to_message(task, time.time_ns()))
                # trigger 'state': input wakes the wait; 'rate': do not sleep past the next tick
                node.spin_once(None if settings.trigger == "state" else min(settings.poll_s, next_rate_tick - now))
                continue
            if settings.trigger == "rate":
                next_rate_tick = max(next_rate_tick + 1.0 / settings.rate_hz, now - 1.0)
            fresh = False
            age_s = (time.time_ns() - latest.header.stamp_ns) / 1e9
            if age_s > settings.max_state_age_s:
                node.counters.count("state_stale")
                node.reject(f"state is {age_s:.3f} s old (limit {settings.max_state_age_s} s): not planning")
                continue
            if -age_s > settings.max_state_future_s:
                node.counters.count("state_future")
                node.reject(f"state stamped {-age_s:.3f} s in the future (limit {settings.max_state_future_s} s): not "
                            "planning; the state source's clock is ahead of this host's")
                continue
            x = state_to_array(latest)
            if previous is not None and (jump := odometry_jump(previous, latest.header.stamp_ns, x, settings)):
                # the warm start was planned for the old pose: from the new one it is a wrong guess
                node.counters.count("odom_jump")
                node.log.warning("%s: warm start reset", jump)
                planner.reset()
            previous = (latest.header.stamp_ns, x)
            cov = None if latest.covariance is None else np.reshape(latest.covariance, (5, 5))
            if cov is not None and (np.any(np.diag(cov) < 0) or not np.allclose(cov, cov.T)):
                node.reject("state covariance is not a covariance (negative variance or asymmetric): planned with "
                            "the configured state_std instead")
                cov = None
            # the command acts once this plan is computed (about as long as the last one) and has reached the base
            delay_s = max(0.0, age_s) + last_plan_s + settings.actuation_delay_s if settings.compensate_delay else 0.0
            try:
                t_plan = time.monotonic()
                result = planner.plan(x, task, weights, state_cov=cov, delay_s=delay_s)
                last_plan_s = time.monotonic() - t_plan
            except (ValueError, FloatingPointError) as exc:
                # no command this cycle: egress's watchdog stops the robot if this persists
                node.error(f"planning failed: {exc}")
                continue
            if not plan_is_finite(result):
                # a state far outside what the model knows (e.g. v = -5 m/s with omega = 20 rad/s) can make the
                # rollouts diverge: such a plan is no plan, so no command (egress's watchdog stops the robot)
                node.counters.count("plan_nonfinite")
                node.error(f"planning from {np.round(x, 3).tolist()} gave non-finite states: no command")
                continue
            cmd = Command(v_ref=float(result.control[0]), omega_ref=float(result.control[1]))
            cmd.header.stamp_ns = latest.header.stamp_ns
            cmd.header.frame_id = "base_link"
            cmd_pub.put(cmd)
            # the control latency as this process sees it: the state's stamp to the command handed to Zenoh
            state_to_cmd_ms = (time.time_ns() - latest.header.stamp_ns) / 1e6
            if cycle == 0:
                startup["to_first_command_s"] = time.monotonic() - t
                startup["process_age_s"] = process_age_s()
                fields = {k: None if v is None else round(v, 3) for k, v in startup.items()}
                node.log.info("first command", extra={"fields": fields})
            if cycle % settings.plan_every == 0:
                try:
                    plan_pub.put(plan_message(result, latest.header.stamp_ns, task, settings.plan_samples,
                                              {"state_to_cmd": state_to_cmd_ms}, terrain.stale))
                except DecodeError as exc:  # e.g. non-finite sample costs: the command went out, the plan cannot
                    node.counters.count("plan_invalid")
                    node.error(f"plan not published: {exc}")
            cycle += 1
            node.cycle()
            node.spin_once(0.0)
    return 0


class TerrainWatch:
    """Whether the terrain weights are current: stale after `weights_stale_after_s` without a valid message, the
    prior after `weights_fallback_after_s`. Weights equal to the prior are never stale: falling back would change
    nothing. That covers the planner before the first message (the terrain service is optional and starts after
    it) and the terrain service's own start, which publishes the prior and then goes quiet while it builds its
    solver."""

    def __init__(self, node: Node, settings: Settings) -> None:
        self.node = node
        self.s = settings
        self.last: float | None = None  # arrival of the last valid weights [monotonic s]
        self.stale = False
        self.on_prior = True
        self._flags()

    def refreshed(self, now: float, weights: np.ndarray) -> None:
        if self.stale:
            self.node.log.info("terrain weights arrive again after %.1f s", now - (self.last or now))
        self.last, self.stale = now, False
        self.on_prior = bool(np.allclose(weights, 1.0 / weights.size, rtol=0.0, atol=1e-9))
        self._flags()

    def check(self, now: float) -> bool:
        """Update the state; True once the weights are to be replaced by the prior."""
        if self.last is None or self.on_prior:
            return False
        silent = now - self.last
        if not self.stale and silent > self.s.weights_stale_after_s:
            self.stale = True
            self.node.counters.count("weights_stale")
            self.node.error(f"no terrain weights for {silent:.1f} s: planning on the last ones (stale)")
            self._flags()
        if not self.on_prior and silent > self.s.weights_fallback_after_s:
            self.on_prior = True
            self.node.counters.count("weights_fallback")
            self.node.error(f"no terrain weights for {silent:.1f} s: planning on the prior (uniform weights)")
            self._flags()
            return True
        return False

    def _flags(self) -> None:
        c = self.node.counters
        with c.lock:
            c.flags["weights_stale"] = self.stale
            c.flags["weights_prior"] = self.on_prior
            c.status = "degraded" if self.stale else "ok"


def _weights_in_model_order(node: Node, msg: TerrainWeights, model: GPModel) -> np.ndarray | None:
    """The weights in the model's terrain order, or None (rejected: the previous ones stay)."""
    terrains = list(model.terrains)
    if sorted(msg.names) != sorted(terrains):
        node.reject(f"terrain weights for {msg.names} but the model has {terrains}: kept the previous weights")
        return None
    by_name = dict(zip(msg.names, msg.weights, strict=True))
    return np.array([by_name[t] for t in terrains], dtype=np.float64)
