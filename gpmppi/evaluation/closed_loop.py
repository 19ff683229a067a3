"""One closed loop in one process: the deployed command path (terrain cycle -> planner cycle -> egress safety) and
the plant, exactly the code the services run.

The plant advances at its own internal step (its `dt`, inside `Plant.step`), the planner runs every
`planner_dt` on the measured state, and a command can reach egress late (latency in seconds; use
`latency_from_cycles` for planner cycles). Egress (`gpmppi.safety.SafetyCycle` with `ClosedLoopConfig.safety`, the
deploy file's limits) sends on each accepted command, at its steady rate and at the watchdog's deadline, and the
plant holds each output until the next (None: the planner's commands reach the plant directly). The terrain
estimator runs in the terrain service's cycle (`gpmppi.terrain.cycle.TerrainCycle`): it gets each state as the
planner does and the commands from `command_source` (egress's first output after accepting a command, stamped with
its state, or the planner's command), solves once the newest state's command is in (after the plan for that state,
as in the stack), and its weights reach the planner for the next state.

The planner is driven through the planner service's own cycle
(`gpmppi.mppi.cycle.PlannerCycle`: weight updates and their ages, state checks, delay compensation) on the
simulation's clock: states are stamped when measured, planning takes no simulated time, and the command latency
is what the cycle compensates (`actuation_delay_s`). Nothing depends on wall-clock time, so a run is a pure
function of its seeds (planner seed, plant seed).

A run stops at the first of: the time limit, the distance limit, a goal task's goal or collision, and an open lane's
end (`finished`: in the lane, within `lane_end_tolerance_m` of the last point along the lane or past it, after
driving at least half the lane's length so a lane that ends where it starts does not finish at once). Closed lanes
have no end: they stop on distance or time.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np

from gpmppi.evaluation.command_path import CommandPath
from gpmppi.evaluation.task_runs import run_for
from gpmppi.mppi.cycle import Planned, PlannerCycle, PlannerLike
from gpmppi.mppi.cycle_config import CycleConfig
from gpmppi.safety import SafetyConfig
from gpmppi.tasks import Task
from gpmppi.terrain.cycle import TerrainCycleConfig
from gpmppi.terrain.estimate import EstimatorLike

Status = Literal["goal", "collision", "finished", "distance", "time_limit", "planner_error", "plant_error"]


class PlantLike(Protocol):
    dt: float

    def reset(self, state: np.ndarray) -> None: ...
    def step(self, command: np.ndarray, duration: float) -> np.ndarray: ...
    def measure(self) -> np.ndarray: ...
    def set_terrain(self, name: str) -> None: ...


@dataclass(frozen=True)
class ClosedLoopConfig:
    """How a closed-loop run is driven and when it stops."""

    planner_dt: float = 0.1  # [s] planning period (the planner's own dt)
    time_limit_s: float = 30.0  # [s] stop after this much simulated time
    distance_limit_m: float | None = None  # [m] stop after driving this far (lanes: 100 m)
    stop_at_goal: bool = True  # goal tasks: stop when the true position is within tolerance
    stop_on_collision: bool = True  # goal tasks: stop at the first overlap with an obstacle
    stop_at_lane_end: bool = True  # open lanes: stop (`finished`) when the robot reaches the last point
    lane_end_tolerance_m: float = 0.5  # [m] open lanes: how far before the last point, along the lane, counts as there
    robot_radius: float = 0.0  # [m] robot disc for collisions (0 = point robot, as the paper scores it)
    latency_s: float = 0.0  # [s] delay between a plan and its command reaching the plant
    compensate_latency: bool = True  # the planner plans from the state predicted `latency_s` ahead (as the service)
    # the planner service's state checks (ages, odometry jumps) and weight ages; its delay settings come from the two
    # fields above
    cycle: CycleConfig = field(default_factory=CycleConfig)
    adapt_weights: bool = True  # run the terrain estimator each cycle and feed its weights to the planner
    terrain_switches: tuple[tuple[float, str], ...] = ()  # (time [s], terrain) changes of the plant's ground
    safety: SafetyConfig | None = None  # egress between the planner and the plant (None: none, commands go direct)
    terrain: TerrainCycleConfig = field(default_factory=TerrainCycleConfig)  # the terrain service's cycle

    def __post_init__(self) -> None:
        if not self.planner_dt > 0 or not self.time_limit_s > 0:
            raise ValueError("planner_dt and time_limit_s must be > 0")
        if self.latency_s < 0:
            raise ValueError(f"latency must be >= 0 s, got {self.latency_s}")
        if not self.lane_end_tolerance_m >= 0:
            raise ValueError(f"lane_end_tolerance_m must be >= 0 m, got {self.lane_end_tolerance_m}")

    def cycle_config(self) -> CycleConfig:
        """The cycle as the service runs it, with this loop's latency as the delay from plan to plant."""
        return self.cycle.model_copy(update={"compensate_delay": self.compensate_latency,
                                             "actuation_delay_s": self.latency_s})


def latency_from_cycles(cycles: int, planner_dt: float = 0.1) -> float:
    """Command latency [s] of a whole number of planner cycles."""
    if cycles < 0:
        raise ValueError(f"latency cycles must be >= 0, got {cycles}")
    return cycles * planner_dt


@dataclass
class Trajectory:
    """What happened in one run, sampled at planner cycles (index k = time k * planner_dt)."""

    times: np.ndarray  # (T+1,) [s]; commands, weights and terrains of cycle k hold from times[k] to times[k+1]
    true_states: np.ndarray  # (T+1, 5)
    measured_states: np.ndarray  # (T+1, 5) what the planner and estimator saw
    commands: np.ndarray  # (T, 2) planned command at cycle k
    weights: np.ndarray  # (T, M) terrain weights used by the plan at cycle k
    weights_ok: np.ndarray  # (T,) whether the estimator produced the weights of that cycle
    planner_ms: np.ndarray  # (T,) wall time of the planner's cycle k (new weights, plan) [ms] (the only
    # non-deterministic field)
    tightened: list[np.ndarray]  # per cycle: lane (N+1,) tightened half-widths or goal (N+1, K) inflated radii
    terrains: list[str]  # plant terrain during cycle k
    status: Status = "time_limit"
    message: str = ""
    plans_xy: list[np.ndarray] = field(default_factory=list)  # nominal plans (N+1, 2) if recorded
    # (T,) each cycle's update's effective sample size (`PlanResult.effective_samples`)
    effective_samples: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # what the base received (egress's outputs; without egress the commands as they reached the plant), each held
    # until the next: times (B,) [s], (B, 2) [v, omega], and each output's reason
    base_times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    base_commands: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    base_reasons: list[str] = field(default_factory=list)
    # each terrain solve: (time [s], stamp of the newest state it answers [ns], weights (M,), solved ok)
    terrain_solves: list[tuple[float, int, np.ndarray, bool]] = field(default_factory=list)
    # (T,) the terrain service's P(unknown ground) and its hysteretic decision as the plan of cycle k had them
    unknown: np.ndarray = field(default_factory=lambda: np.zeros(0))
    unknown_active: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    # (T,) whether the weights the plan of cycle k used named a top ground (TerrainEstimate.identified; empty: all)
    identified: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    @property
    def positions(self) -> np.ndarray:
        return self.true_states[:, :2]


@dataclass(frozen=True)
class _Cycle:
    """What one planner cycle of a run recorded (a `Trajectory` row)."""

    command: np.ndarray  # (2,) the planned command
    weights: np.ndarray  # (M,) the terrain weights the plan used
    weights_ok: bool  # whether the estimator produced them
    planner_ms: float  # wall time of the planner's cycle [ms]
    tightened: np.ndarray  # the plan's tightened half-widths or inflated radii
    terrain: str  # the plant's terrain
    effective_samples: float  # the update's effective sample size
    plan_xy: np.ndarray | None  # the nominal plan (N+1, 2), if recorded
    unknown: float = 0.0  # the last terrain solve's P(unknown ground)
    unknown_active: bool = False  # and its hysteretic decision (the planner's caution)
    identified: bool = True  # whether the weights named a top ground (TerrainEstimate.identified)


def _trajectory(
    times: list[float], trues: list[np.ndarray], meas: list[np.ndarray], cycles: list[_Cycle], n_terrains: int,
    status: Status, message: str, record_plans: bool, path: CommandPath,
) -> Trajectory:
    m = len(cycles)
    return Trajectory(
        times=np.asarray(times),
        true_states=np.asarray(trues),
        measured_states=np.asarray(meas),
        commands=np.asarray([c.command for c in cycles]).reshape(m, 2),
        weights=np.asarray([c.weights for c in cycles]).reshape(m, n_terrains),
        weights_ok=np.asarray([c.weights_ok for c in cycles], dtype=bool),
        planner_ms=np.asarray([c.planner_ms for c in cycles]),
        tightened=[c.tightened for c in cycles],
        terrains=[c.terrain for c in cycles],
        status=status,
        message=message,
        plans_xy=[c.plan_xy for c in cycles] if record_plans else [],
        effective_samples=np.asarray([c.effective_samples for c in cycles], dtype=np.float64),
        base_times=np.asarray(path.base_times, dtype=np.float64),
        base_commands=np.asarray(path.base_commands, dtype=np.float64).reshape(-1, 2),
        base_reasons=list(path.base_reasons),
        terrain_solves=list(path.solves),
        unknown=np.asarray([c.unknown for c in cycles], dtype=np.float64),
        unknown_active=np.asarray([c.unknown_active for c in cycles], dtype=bool),
        identified=np.asarray([c.identified for c in cycles], dtype=bool),
    )


def run_closed_loop(
    planner: PlannerLike,
    plant: PlantLike,
    task: Task,
    start: np.ndarray,
    n_terrains: int,
    config: ClosedLoopConfig | None = None,
    estimator: EstimatorLike | None = None,  # the terrain estimator (None: the planner keeps its weights)
    initial_weights: np.ndarray | None = None,
    initial_terrain: str | None = None,
    record_plans: bool = False,
) -> Trajectory:
    """Drive `plant` with `planner` on `task` from `start` until goal, collision, lane end, distance or time limit."""
    cfg = config or ClosedLoopConfig()
    dt = cfg.planner_dt
    eps = 1e-9
    switches = sorted(cfg.terrain_switches)
    terrain = initial_terrain or ""
    if initial_terrain is not None:
        plant.set_terrain(initial_terrain)
    planner.reset()
    # the simulation's clock: it stands still while the planner plans
    sim_now = [0.0]
    cycle = PlannerCycle(planner, task, cfg.cycle_config(), n_terrains, clock=lambda: sim_now[0])
    if initial_weights is not None and not cycle.on_weights(initial_weights, 0.0):
        raise ValueError(f"initial_weights: {cycle.drain_events()[-1].message}")
    plant.reset(np.asarray(start, dtype=np.float64))
    true_state = np.asarray(start, dtype=np.float64).copy()
    measured = np.asarray(plant.measure(), dtype=np.float64)
    prepare = getattr(planner, "prepare_task", None)
    delayed = cfg.compensate_latency and cfg.latency_s > 0.0  # the first state's own age and plan time are 0 here
    if prepare is not None and not delayed:
        # what the task's plans read once (a goal field, a lane lookup) is built now, off the steps' clock, as the
        # service does when a task comes after a state: a one-off per task, which the first model of a process
        # paid and the others found cached. Only without a delay: a delayed first plan starts from a predicted
        # state, from where it places its goal field's grid
        prepare(task, measured)

    times, trues, meas = [0.0], [true_state.copy()], [measured.copy()]
    cycles: list[_Cycle] = []
    path = CommandPath(cfg.safety, cfg.terrain, n_terrains, estimator if cfg.adapt_weights else None)
    driven = 0.0
    status: Status = "time_limit"
    message = ""
    steps = int(np.ceil(cfg.time_limit_s / dt - eps))
    run = run_for(task)  # when the task stops the run: a goal task's goal or collision, an open lane's end
    for k in range(steps):
        t = k * dt
        sim_now[0] = t
        while switches and switches[0][0] <= t + eps:
            terrain = switches.pop(0)[1]
            plant.set_terrain(terrain)
        stamp_ns = round(t * 1e9)
        # the state reaches the terrain service and the planner together; the planner plans on the weights of the
        # last solve (the terrain service solves for this state once its command is out)
        path.on_state(stamp_ns, measured, t)
        t0 = time.perf_counter()
        out = cycle.on_state(measured, stamp_ns, t, stamp_ns)
        if not isinstance(out, Planned):
            status, message = "planner_error", f"planner refused at t={t:.1f} s ({out.name}): {out.message}"
            break
        result = out.result
        planner_ms = (time.perf_counter() - t0) * 1e3
        command = np.asarray(result.control, dtype=np.float64).copy()
        record = _Cycle(
            command=command, weights=cycle.weights.copy(), weights_ok=path.weights_ok, planner_ms=planner_ms,
            tightened=np.asarray(result.tightened).copy(), terrain=terrain,
            effective_samples=float(result.effective_samples),
            plan_xy=np.asarray(result.states)[:, :2].copy() if record_plans else None,
            unknown=path.unknown[-1][1] if path.unknown else 0.0, unknown_active=cycle.unknown_active,
            identified=path.identified,
        )
        path.on_planned(t, t + cfg.latency_s, stamp_ns, command)

        # advance the plant over [t, t + dt): egress's outputs and the terrain solve happen on their own times
        try:
            true_state = path.advance(plant, t, t + dt, cycle)
        except FloatingPointError as e:
            status, message = "plant_error", f"plant failed in [{t:.2f}, {t + dt:.2f}) s: {e}"
            break  # the cycle whose plant step failed is not recorded
        cycles.append(record)
        measured = np.asarray(plant.measure(), dtype=np.float64).copy()
        driven += float(np.linalg.norm(true_state[:2] - trues[-1][:2]))
        times.append((k + 1) * dt)
        trues.append(true_state.copy())
        meas.append(measured.copy())

        if not np.all(np.isfinite(true_state)):
            status, message = "plant_error", f"plant state became non-finite at t={times[-1]:.1f} s"
            break
        stop = run.stop(true_state, driven, cfg)
        if stop is not None:
            status = stop
            break
        if cfg.distance_limit_m is not None and driven >= cfg.distance_limit_m:
            status = "distance"
            break

    return _trajectory(times, trues, meas, cycles, n_terrains, status, message, record_plans, path)
