"""planner: GP-MPPI on each new state (or at a fixed rate) with the newest terrain weights and task.

Publishes `cmd` (stamped with the state's stamp, so stamp -> publish is the control latency) and `plan`
(nominal trajectory, position covariances, tightened bounds, a subset of rollouts, timings). The task is the
configured scenario's, re-published once a second on `task`; a Task from another publisher replaces it.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import Field

from gpmppi.mppi.config import PlannerConfig  # not the planner module: run() imports it alongside the model load
from schemas import Command, Plan, State, TerrainWeights
from services.convert import state_to_array, task_from_message, task_to_message
from services.node import Node, NodeSettings
from services.scheduling import process_age_s

if TYPE_CHECKING:
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
    compensate_delay: bool = Field(
        True,
        description="plan from the state predicted to when the command takes effect (state age + compute + "
        "actuation_delay_s), not from the measured one; the age is this host's clock minus the state's stamp, so "
        "the two clocks must agree (one host, or synchronised clocks): turn it off otherwise",
    )
    actuation_delay_s: float = Field(
        0.005, ge=0, le=0.5, description="from publishing `cmd` to the base applying it (egress hop, base tick) [s]"
    )
    plan_samples: int = Field(16, ge=0, description="rollouts (XY) included in each Plan message")
    plan_every: int = Field(1, ge=1, description="publish a Plan every n-th cycle (cmd every cycle)")
    task_period_s: float = Field(1.0, gt=0, description="re-publish the task this often [s]")


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


def plan_message(
    result: PlanResult,
    stamp_ns: int,
    task: LaneTask | GoalTask,
    n_samples: int,
    extra_timings_ms: dict[str, float] | None = None,
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
        state_sub = node.subscribe("state")
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
            if (w := weights_sub.take()) is not None:
                new_weights = _weights_in_model_order(node, w, model.terrains, weights)
                try:
                    # new weights arrive between states (terrain solves after each command): the table collapse
                    # for them is done now, not on the next state's path to its command
                    planner.prepare(new_weights)
                    weights = new_weights
                except ValueError as exc:
                    node.reject(f"terrain weights: {exc}; kept the previous weights")
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
                node.reject(f"state is {age_s:.3f} s old (limit {settings.max_state_age_s} s): not planning")
                continue
            cov = None if latest.covariance is None else np.reshape(latest.covariance, (5, 5))
            if cov is not None and (np.any(np.diag(cov) < 0) or not np.allclose(cov, cov.T)):
                node.reject(
                    "state covariance is not a covariance (negative variance or asymmetric): planned with "
                    "the configured state_std instead"
                )
                cov = None
            # the command acts once this plan is computed (about as long as the last one) and has reached the base
            delay_s = max(0.0, age_s) + last_plan_s + settings.actuation_delay_s if settings.compensate_delay else 0.0
            try:
                t_plan = time.monotonic()
                result = planner.plan(state_to_array(latest), task, weights, state_cov=cov, delay_s=delay_s)
                last_plan_s = time.monotonic() - t_plan
            except (ValueError, FloatingPointError) as exc:
                # no command this cycle: egress's watchdog stops the robot if this persists
                node.error(f"planning failed: {exc}")
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
                plan_pub.put(
                    plan_message(
                        result, latest.header.stamp_ns, task, settings.plan_samples, {"state_to_cmd": state_to_cmd_ms}
                    )
                )
            cycle += 1
            node.cycle()
            node.spin_once(0.0)
    return 0


def _weights_in_model_order(
    node: Node, msg: TerrainWeights, terrains: list[str], previous: np.ndarray | None
) -> np.ndarray | None:
    if sorted(msg.names) != sorted(terrains):
        node.reject(f"terrain weights for {msg.names} but the model has {terrains}: kept the previous weights")
        return previous
    by_name = dict(zip(msg.names, msg.weights, strict=True))
    return np.array([by_name[t] for t in terrains], dtype=np.float64)
