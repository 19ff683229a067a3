"""planner: GP-MPPI on each new state (or at a fixed rate) with the newest terrain weights and task.

Publishes `cmd` (stamped with the state's stamp, so stamp -> publish is the control latency) and `plan`
(nominal trajectory, position covariances, tightened bounds, a subset of rollouts, timings). The task is the
configured scenario's, re-published once a second on `task`; a Task from another publisher replaces it.

Under faults (docs/safety.md): stale, future-stamped (clock skew) and non-finite states are refused and counted by
name in the heartbeat; silent terrain weights are kept but flagged (`Plan.weights_stale`, heartbeat flag
`weights_stale`, status degraded) and after `weights_fallback_after_s` replaced by the prior (uniform, what the
terrain service itself publishes first); an odometry jump (teleport, relocalisation) resets the warm start.

Everything between a state arriving and its command leaving is `gpmppi.mppi.cycle.PlannerCycle`, which the
closed-loop evaluation drives too; this module decodes, drives it, encodes, publishes and counts. When the
kernels are not in numba's cache yet, the log says so before compiling them, with an estimate.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import Field, ValidationError

from gpmppi.mppi.config import PlannerConfig  # not the planner module: start() imports it alongside the model load
from gpmppi.mppi.cycle import Event, Planned, PlannerCycle
from gpmppi.mppi.cycle_config import CycleConfig
from schemas import DecodeError, OccupancyGrid, Plan, State, decode
from services.codec.convert import (
    costmap_from_message,
    state_to_array,
    task_from_message,
    task_to_message,
)
from services.model_swap import ModelSwap, model_version, profile_sha256, take_swap
from services.planner_outputs import Outputs, Ros2PlanOutput
from services.runtime.node import Node, TypedSubscription
from services.runtime.node_settings import NodeSettings
from services.runtime.scheduling import process_age_s

if TYPE_CHECKING:
    import zenoh

    from gpmppi.gp.model_file import GPModel
    from gpmppi.mppi.planner import Planner
    from gpmppi.scenarios import Scenario


class Settings(NodeSettings, CycleConfig):
    """The planner service's settings; the planning cycle's checks and delay compensation (`CycleConfig`) are
    top-level fields."""

    service: str = Field("planner", description="service name")
    planner: PlannerConfig = Field(default_factory=PlannerConfig, description="GP-MPPI settings")
    scenario: str = Field(
        "circle", description="task: 'circle', 'square', 'paper_obstacles', a lane_*.yaml / scene_*.yaml file, or "
        "'none' (no task until one arrives on `task`, e.g. from the nav service: nothing is planned until then, so "
        "egress holds the robot at zero)"
    )
    model_file: str | None = Field(None, description="the robot profile (.npz from `gpmppi train`; a launch "
                                   "file's top-level `profile` fills it; None: the shipped Jackal profile)")
    learned_dir: str | None = Field(None, description="a folder that also holds announced profiles as "
                                    "<sha256>.npz, taken before the announced path (replay puts a recording's "
                                    "learned profiles there)")
    trigger: Literal["state", "rate"] = Field("state", description="plan on each new state, or at rate_hz")
    rate_hz: float = Field(10.0, gt=0, description="planning rate when trigger == 'rate' [Hz]")
    actuation_delay_s: float = Field(
        0.005, ge=0, le=0.5, description="from publishing `cmd` to the base applying it (egress hop, base tick) [s]"
    )
    plan_samples: int = Field(16, ge=0, description="rollouts (XY) included in each Plan message")
    plan_every: int = Field(1, ge=1, description="publish a Plan every n-th cycle (cmd every cycle)")
    task_period_s: float = Field(1.0, gt=0, description="re-publish the task this often [s]")
    ros2_plan: Ros2PlanOutput = Field(
        default_factory=Ros2PlanOutput, description="the plan for ROS 2: nav_msgs/Path in the state's (odometry's) "
        "frame, one pose per step stamped when the plan reaches it; with every Plan (`plan_every`)"
    )

    def cycle_config(self) -> CycleConfig:
        return CycleConfig(**{name: getattr(self, name) for name in CycleConfig.model_fields})


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
        return msg


NO_TASK = "none"  # the `scenario` of a planner that waits for its task on `task`


def warm_up_scenario(name: str) -> Scenario:
    """The scenario the kernels are compiled on before going live: the configured one, the circle for 'none'."""
    return load_scenario("circle" if name == NO_TASK else name)


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


def log_model_fit(log: logging.Logger | logging.LoggerAdapter, model: GPModel, model_file: str | None) -> int:
    """Repeat the model file's training warnings (a task whose GP was worse than the nominal model on held-out
    data) in the start-up log; the number of warnings."""
    lines = model.fit_warnings()
    for line in lines:
        log.warning("model %s: %s", model_file or "(shipped default)", line)
    return len(lines)


def run(settings: Settings) -> int:
    """Start the planner (model, kernels, a warm-up plan), then run its live loop until the node stops."""
    node, planner, scenario, startup = start(settings)
    with node:
        PlannerLoop(node, settings, planner, scenario, startup).run()
    return 0


def start(settings: Settings) -> tuple[Node, Planner, Scenario, dict[str, float]]:
    """Load the model and the scenario, open nothing yet, build the planner and warm its kernels up; the node, the
    planner, the warm-up scenario and where the start spent its time [s]."""
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

        scenario = warm_up_scenario(settings.scenario)
        model = loading.result()
    startup["planner_import_and_model_s"] = time.monotonic() - t
    # everything that does not need the session is done before it opens: the kernels loaded (or compiled) and the
    # warm-up plan. A process started ahead of need waits in `Node.open` ready to plan (services.runtime.role).
    node = Node(settings)
    log_model_fit(node.log, model, settings.model_file)
    t = time.monotonic()
    planner = Planner(settings.planner, model)
    warm_up(node, planner, scenario)
    startup["warmup_s"] = time.monotonic() - t
    return node, planner, scenario, startup


class PlannerLoop:
    """The live loop, in the order of one pass: take the newest inputs, then plan and publish when a plan is due,
    else re-publish the task and wait for input."""

    def __init__(self, node: Node, settings: Settings, planner: Planner, scenario: Scenario,
                 startup: dict[str, float]) -> None:
        model = planner.model
        self.node, self.settings = node, settings
        # the newest state, weights and task are taken the moment they arrive
        self.state_sub = StateSubscription(node, node.key("state"), State, newest_only=True, capacity=1024)
        self.weights_sub = node.subscribe("terrain_weights")
        self.task_sub = node.subscribe("task", remote_only=True)  # our own re-publications must not loop back
        self.costmap_sub = node.subscribe("costmap", remote_only=True)
        self.model_sub = node.subscribe("model_update")
        self.swap = ModelSwap(settings.planner, profile_sha256(settings.model_file), model_version(model),
                              search_dir=settings.learned_dir)
        self.pending_grid: OccupancyGrid | None = None  # a grid that came before the first state (frame unchecked)
        self.outputs = Outputs(node, settings, settings.planner.dt, startup)
        self.outputs.model_version = self.swap.version
        self.outputs.started = time.monotonic()
        initial_task = None if settings.scenario == NO_TASK else scenario.task
        self.cycle = PlannerCycle(planner, initial_task, settings.cycle_config(), len(model.terrains), model.terrains)
        if (last := node.handed_over("plan", Plan)) is not None:
            # a predecessor's last plan (the launcher saw it): the first plan starts from its sequence, shifted to
            # the first state, never from zero commands at speed
            self.cycle.resume_from(last.controls, last.header.stamp_ns, settings.planner.dt)
            if last.terrain_weights and len(last.terrain_weights) == len(model.terrains):
                self.cycle.on_weights(last.terrain_weights, time.monotonic())
        self.report = CycleReport(node, self.cycle)
        self.next_task = 0.0  # when to re-publish the task next [s, monotonic]
        self.next_rate_tick = time.monotonic()  # trigger 'rate': when the next plan is due [s, monotonic]
        self.latest: State | None = None  # the newest state
        self.fresh = False  # `latest` has not been planned from yet

    def run(self) -> None:
        """Pass after pass until the node stops: inputs, then a plan and its outputs, or the task and a wait."""
        while self.node.ok():
            now = time.monotonic()
            self.take_inputs(now)
            if (state := self.due(now)) is None:
                self.between_cycles(now)
                continue
            if (out := self.plan(state, now)) is not None:
                self.publish(out, state)
            self.node.spin_once(0.0)

    def take_inputs(self, now: float) -> None:
        """Take what arrived since the last pass: a model update, a task, a costmap, weights, then the newest state."""
        self.take_model()
        self.take_task()
        self.take_costmap(now)
        self.take_weights(now)
        self.cycle.tick(now)
        self.report(self.cycle.drain_events())
        if (s := self.state_sub.take()) is not None:
            self.latest, self.fresh = s, True

    def take_model(self) -> None:
        """Offer an announced model update to the swap, and plan with a swapped-in model from the next state on."""
        if (update := self.model_sub.take()) is not None and (line := self.swap.offer(update)) is not None:
            self.node.log.info(line)
        if (ready := self.swap.take()) is not None:  # between plans: the next state plans with the new model
            take_swap(self.node, self.cycle, ready, self.outputs)

    def take_task(self) -> None:
        """Plan a task from another publisher from now on (refused with its reason when it is not a valid task)."""
        if (new_task := self.task_sub.take()) is not None:
            try:
                self.cycle.set_task(task_from_message(new_task))
                self.node.log.info("new task: %s", new_task.kind)
            except ValueError as exc:
                self.node.reject(f"task: {exc}")

    def take_costmap(self, now: float) -> None:
        """Take a new grid once a state has come, since its frame is checked against the states'."""
        if (grid := self.costmap_sub.take()) is not None:
            self.pending_grid = grid
        if self.pending_grid is not None and self.latest is not None:
            take_costmap(self.node, self.cycle, self.pending_grid, self.latest.header.frame_id, now)
            self.pending_grid = None

    def take_weights(self, now: float) -> None:
        """Hand new terrain weights to the cycle; those for a model still loading only mark the weights pending."""
        if (w := self.weights_sub.take()) is not None:
            if tuple(w.names) == self.swap.loading:  # for the model loading: they wait for it (not refused)
                self.cycle.weights_pending(now)
            else:
                self.cycle.on_weights(w.weights, now, names=w.names, unknown_active=w.unknown_active,
                                      unknown_channel=w.unknown_channel)

    def due(self, now: float) -> State | None:
        """The state to plan from now: the newest on a new one (trigger 'state') or at the rate's tick (trigger
        'rate'); None when no plan is due."""
        due = self.fresh if self.settings.trigger == "state" else now >= self.next_rate_tick
        return self.latest if due else None

    def between_cycles(self, now: float) -> None:
        """Re-publish the task (and its grid) when its period is up, then wait for input or the next rate tick."""
        settings, cycle = self.settings, self.cycle
        if now >= self.next_task and cycle.task is not None:
            # only here, between cycles: never on a state's path to its command (encoding the lane's polyline
            # takes milliseconds; a cycle with it on the path measured 22.9 ms, the median 5)
            self.next_task = now + settings.task_period_s
            self.outputs.task.put(task_to_message(cycle.task, time.time_ns()))
            if (grid_msg := self.outputs.grid_message(cycle.task, self.latest)) is not None:
                self.outputs.costmap.put(grid_msg)
        # trigger 'state': input wakes the wait; 'rate': do not sleep past the next tick
        self.node.spin_once(None if settings.trigger == "state" else min(settings.poll_s, self.next_rate_tick - now))

    def plan(self, latest: State, now: float) -> Planned | None:
        """Run the cycle on the state; its plan, or None when the cycle refused the state or did not plan."""
        if self.settings.trigger == "rate":
            self.next_rate_tick = max(self.next_rate_tick + 1.0 / self.settings.rate_hz, now - 1.0)
        self.fresh = False
        out = self.cycle.on_state(state_to_array(latest), latest.header.stamp_ns, now, time.time_ns(),
                                  latest.covariance)
        self.report(self.cycle.drain_events())
        # no command this cycle: egress's watchdog stops the robot if it lasts
        return out if isinstance(out, Planned) else None

    def publish(self, out: Planned, state: State) -> None:
        """Publish the command and (every `plan_every`-th cycle) the plan in the state's frame, and count the cycle
        in the heartbeat."""
        self.outputs.publish(out, self.cycle.task, state.header.frame_id)
        self.node.cycle()


def take_costmap(node: Node, cycle: PlannerCycle, msg: OccupancyGrid, state_frame: str,
                 now: float | None = None) -> bool:
    """Plan goal tasks among the grid of `msg` from now on; refused (counted by name in the heartbeat,
    `costmap_frame` / `costmap_invalid`, and in its rejects with the reason) when it is not in the states' frame or
    not a valid grid."""
    if msg.header.frame_id != state_frame:
        node.counters.count("costmap_frame")
        node.reject(f"costmap: grid in frame {msg.header.frame_id!r}, but the states are in {state_frame!r}; publish "
                    f"the grid in {state_frame!r} (the planner does not transform it)")
        return False
    try:
        cycle.set_costmap(costmap_from_message(msg), now)
    except ValueError as exc:
        node.counters.count("costmap_invalid")
        node.reject(f"costmap: {exc}")
        return False
    node.log.info("new costmap: %d x %d cells of %.3f m in %s", msg.width, msg.height, msg.resolution, state_frame)
    return True


def warm_up(node: Node, planner: Planner, scenario: Scenario) -> None:
    """Compile or load the kernels before going live (`kernel_cache.warm_up`: a notice first when they have to be
    compiled, afterwards how long it took)."""
    from gpmppi.mppi import kernel_cache

    c = planner.config
    start = np.asarray(scenario.start, dtype=np.float64)

    kernel_cache.warm_up(kernel_cache.planner_label(c.dynamics, c.gp_mode, planner.backend),
                         lambda: planner.warm_up(start, scenario.task), node.log.info)


class CycleReport:
    """The cycle's events into the heartbeat's counters and the log, and the terrain weights' state into its
    flags (`weights_stale`, `weights_prior`, `caution`: planning carefully on unknown ground) and status (degraded
    while stale)."""

    def __init__(self, node: Node, cycle: PlannerCycle) -> None:
        self.node, self.cycle = node, cycle
        self.shown: tuple[bool, bool, bool] | None = None
        self([])

    def __call__(self, events: list[Event]) -> None:
        node = self.node
        for e in events:
            node.counters.count(e.name)
            if e.level == "reject":
                node.reject(e.message)
            elif e.level == "error":
                node.error(e.message)
            elif e.level == "warning":
                node.log.warning(e.message)
            elif e.level == "count":
                continue
            else:
                node.log.info(e.message)
        state = (self.cycle.weights_stale, self.cycle.weights_prior, self.cycle.unknown_active)
        if state != self.shown:
            self.shown = state
            c = node.counters
            with c.lock:
                c.flags["weights_stale"], c.flags["weights_prior"], c.flags["caution"] = state
                c.status = "degraded" if state[0] else "ok"
