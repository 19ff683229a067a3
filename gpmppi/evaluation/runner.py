"""Build planner, estimator and plant for one evaluation job, run its trials and score them.

A job is one (scenario, terrain, model) cell with a list of seeds. Jobs are plain picklable data so
the table can fan them out to worker processes (spawn context); each worker keeps its GP model
and terrain set in a small per-process cache.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np

from gpmppi.evaluation.closed_loop import ClosedLoopConfig, Trajectory, run_closed_loop
from gpmppi.evaluation.metrics import (
    command_rates,
    mean_p95,
    mean_std,
    path_length,
    true_weight_mean,
    unidentified_share,
    unknown_delay_s,
    unknown_share,
    weight_switches_per_min,
)
from gpmppi.evaluation.task_runs import run_for
from gpmppi.safety import SafetyConfig
from gpmppi.scenarios import Scenario, infeasibility, random_obstacle_scene
from gpmppi.tasks import Task
from gpmppi.terrain.cycle import TerrainCycleConfig
from gpmppi.terrain.estimate import EstimatorLike, TerrainEstimate

Dynamics = Literal["gp", "edd5", "unicycle"]
PlantKind = Literal["physics", "residual-net"]
MODELS: tuple[Dynamics, ...] = ("gp", "edd5", "unicycle")
# The paper's residual net orders its six outputs as the CSV columns: Asphalt, Grass, Tile (v then omega each).
PAPER_NET_TERRAINS = ["asphalt", "grass", "tile"]


@dataclass(frozen=True)
class EvalSettings:
    """Everything about an evaluation that is shared by all its jobs."""

    plant: PlantKind = "physics"
    plant_file: str | None = None  # residual-net: the network JSON (the paper's fcnn.json)
    terrain_file: str | None = None  # physics: terrain set YAML (None = shipped)
    gp_model: str | None = None  # GP model file (None = shipped default)
    samples: int = 1024
    horizon: int = 40
    backend: Literal["auto", "cpu", "cuda"] = "cpu"
    lane_distance_m: float = 100.0  # lanes: drive this far at the speed target
    goal_time_limit_s: float = 30.0  # avoidance: time limit for success
    sensor_noise: bool = True  # physics plant measurement noise
    latency_s: float = 0.0  # command latency
    compensate_latency: bool = True  # planners plan for the state their command meets (`ClosedLoopConfig`)
    robot_radius: float = 0.0  # collision radius of the robot (0 = point, as the paper scores)
    planner_overrides: tuple[tuple[str, object], ...] = ()  # extra PlannerConfig fields, same for every model
    terrain_estimator: tuple[tuple[str, object], ...] = ()  # EstimatorConfig fields (gpmppi.terrain.settings)
    oracle_weights: bool = False  # GP-MPPI gets the true terrain's one-hot weights (uniform on an unknown terrain)
    # the deployed command path (`gpmppi.evaluation.deployed.deployed_path` reads them from a launch file): egress's
    # safety between planner and plant (None: commands reach the plant directly), and the terrain service's cycle
    safety: SafetyConfig | None = field(default_factory=SafetyConfig)
    terrain_cycle: TerrainCycleConfig = field(default_factory=TerrainCycleConfig)


@dataclass(frozen=True)
class Job:
    """One table cell: a scenario on a terrain with one model, for the given seeds."""

    kind: Literal["tracking", "avoidance"]
    scenario: Scenario
    terrain: str
    dynamics: Dynamics
    seeds: tuple[int, ...]
    record: bool = False  # keep the first seed's trajectory (for figures)
    terrain_switches: tuple[tuple[float, str], ...] = ()
    label: str = ""  # the task column this job feeds (circle, square, avoidance, a file name)
    random_scenes: bool = False  # avoidance: each seed drives its own random scene (`random_obstacle_scene(seed)`)


@dataclass
class RunScore:
    """The numbers of one trial."""

    seed: int
    status: str
    rmse_mm: float = float("nan")
    lane_exits: int = 0
    success: bool = False
    time_to_goal_s: float = float("nan")
    min_clearance_m: float = float("nan")
    distance_m: float = 0.0
    mean_speed_mps: float = float("nan")
    planner_ms_mean: float = float("nan")
    planner_ms_p95: float = float("nan")
    v_ref_rate_mean: float = float("nan")  # [m/s^2] mean |change of v_ref| / dt between consecutive commands
    v_ref_rate_p95: float = float("nan")  # [m/s^2] its 95th percentile
    omega_ref_rate_mean: float = float("nan")  # [rad/s^2] mean |change of omega_ref| / dt
    omega_ref_rate_p95: float = float("nan")  # [rad/s^2] its 95th percentile
    # the update's effective sample size over the run's plans (Kish; `PlanResult.effective_samples`)
    effective_samples_p50: float = float("nan")
    effective_samples_p10: float = float("nan")
    # the same of the commands the base received (egress's outputs, after its limits), between consecutive outputs
    base_v_rate_mean: float = float("nan")  # [m/s^2]
    base_v_rate_p95: float = float("nan")
    base_omega_rate_mean: float = float("nan")  # [rad/s^2]
    base_omega_rate_p95: float = float("nan")
    base_limited_fraction: float = float("nan")  # share of the base's commands that an egress limit changed
    true_weight_mean: float | None = None  # time-averaged weight of the terrain driven on, after the first 3 s
    # (None: a model without terrain weights, a terrain the model does not know, or nothing after 3 s)
    weight_switches_per_min: float | None = None  # changes of the top-weight terrain per minute (None: no weights)
    # share of the time after the first 3 s whose weights named no top ground (TerrainEstimate.identified)
    top_unidentified_share: float | None = None
    # share of the time on trained grounds with P(unknown ground) > 0.5 (None: no estimator or no such time)
    unknown_share: float | None = None
    # seconds from reaching a ground the model was not trained on until P(unknown) > 0.5 (inf: never; None: none)
    unknown_delay_s: float | None = None
    unknown_active_share: float | None = None  # share of the run's time planned with the caution on
    # share of the time on grounds the model was not trained on with P(unknown) > 0.5 (None: no such time)
    unknown_new_share: float | None = None
    final_weights: list[float] = field(default_factory=list)
    message: str = ""


@functools.lru_cache(maxsize=4)
def cached_gp_model(path: str | None):
    from gpmppi.gp.model_file import GPModel, load_default_model

    return load_default_model() if path is None else GPModel.load(path)


@functools.lru_cache(maxsize=4)
def cached_terrain_set(path: str | None):
    from gpmppi.plant.terrains import load_terrains

    return load_terrains(path)


def make_plant(settings: EvalSettings, terrain: str, seed: int):
    """The plant of this evaluation on `terrain`, seeded."""
    if settings.plant == "physics":
        from gpmppi.plant.physics import PhysicsPlant

        return PhysicsPlant(cached_terrain_set(settings.terrain_file), terrain, seed=seed, noise=settings.sensor_noise)
    from gpmppi.plant.residual_net import ResidualNetPlant

    if settings.plant_file is None:
        raise ValueError("the residual-net plant needs --plant-file (the network JSON, e.g. the paper's fcnn.json)")
    model = cached_gp_model(settings.gp_model)
    return ResidualNetPlant(settings.plant_file, model.theta, terrain, PAPER_NET_TERRAINS, seed=seed)


def make_planner(settings: EvalSettings, dynamics: Dynamics, terrain: str, seed: int):
    """A planner with the given model; EDD5 uses the parameters of the terrain it drives on when it has them."""
    from gpmppi.mppi.planner import Planner, PlannerConfig

    model = cached_gp_model(settings.gp_model)
    edd5_terrain = terrain if (dynamics == "edd5" and terrain in model.edd5) else None
    fields: dict[str, object] = {
        "backend": settings.backend,
        "samples": settings.samples,
        "horizon": settings.horizon,
        "robot_radius": settings.robot_radius,
    }
    fields.update(settings.planner_overrides)
    fields.update(dynamics=dynamics, seed=seed, edd5_terrain=edd5_terrain)
    return Planner(PlannerConfig(**fields), model)


class OracleEstimator:
    """Stands in for the terrain estimator with the truth: one-hot weights of the terrain under the plant now.

    On a terrain the model was not trained on (sand) it gives uniform weights, as there is no true weight. An
    `EstimatorLike` that needs no history.
    """

    min_history = 0

    def __init__(self, plant, terrain_names: list[str]) -> None:
        self.plant = plant
        self.names = list(terrain_names)

    @property
    def weights(self) -> np.ndarray:
        return self.estimate().weights

    def __len__(self) -> int:
        return 0

    def observe(self, state: np.ndarray, command: np.ndarray, next_state: np.ndarray) -> None:
        pass

    def estimate(self) -> TerrainEstimate:
        m = len(self.names)
        terrain = getattr(self.plant, "terrain", None)
        if terrain in self.names:
            w = np.zeros(m)
            w[self.names.index(terrain)] = 1.0
            return TerrainEstimate(w, True, 0.0, f"oracle: the plant is on {terrain}")
        return TerrainEstimate(np.full(m, 1.0 / m), True, 0.0, f"oracle: {terrain!r} is not a model terrain")


def make_terrain_estimator(settings: EvalSettings, plant) -> EstimatorLike:
    """The terrain estimator of this evaluation (`settings.terrain_estimator`), or the oracle."""
    model = cached_gp_model(settings.gp_model)
    if settings.oracle_weights:
        return OracleEstimator(plant, list(model.terrains))
    from gpmppi.terrain.estimator import make_estimator
    from gpmppi.terrain.settings import EstimatorConfig

    return make_estimator(model, EstimatorConfig(**dict(settings.terrain_estimator)))


def needs_estimator(settings: EvalSettings, job: Job) -> bool:
    """GP-MPPI always adapts its weights; EDD5 does on a terrain it has no parameters for (it takes the top weight)."""
    if job.dynamics == "gp":
        return True
    return job.dynamics == "edd5" and job.terrain not in cached_gp_model(settings.gp_model).edd5


def loop_config(settings: EvalSettings, job: Job) -> ClosedLoopConfig:
    task = job.scenario.task
    adapt = needs_estimator(settings, job)
    limits = run_for(task).limits(settings.lane_distance_m, settings.goal_time_limit_s)
    return ClosedLoopConfig(
        **limits,
        latency_s=settings.latency_s,
        compensate_latency=settings.compensate_latency,
        robot_radius=settings.robot_radius,
        adapt_weights=adapt,
        terrain_switches=job.terrain_switches,
        safety=settings.safety,
        terrain=settings.terrain_cycle,
    )


def score(
    traj: Trajectory, task: Task, seed: int, cfg: ClosedLoopConfig,
    terrain_names: list[str] | None = None,
) -> RunScore:
    """Score one trajectory (true states, at planner cycles).

    The run's scores cover what it drove: it stops at an open lane's end (`finished`), so RMSE and mean speed never
    include waiting there. `terrain_names` are the model's terrains (the columns of the weights), for a model whose
    weights are estimated (`cfg.adapt_weights`); otherwise the weight scores stay None.
    """
    pos = traj.positions
    s = RunScore(seed=seed, status=traj.status, message=traj.message, distance_m=path_length(pos))
    if traj.times[-1] > 0:
        s.mean_speed_mps = s.distance_m / float(traj.times[-1])
    if traj.planner_ms.size:
        s.planner_ms_mean = float(np.mean(traj.planner_ms))
        s.planner_ms_p95 = float(np.percentile(traj.planner_ms, 95))
    if traj.weights.size:
        s.final_weights = [float(w) for w in traj.weights[-1]]
    rates = command_rates(traj.times, traj.commands)
    s.v_ref_rate_mean, s.v_ref_rate_p95 = mean_p95(rates[:, 0])
    s.omega_ref_rate_mean, s.omega_ref_rate_p95 = mean_p95(rates[:, 1])
    if traj.effective_samples.size:
        s.effective_samples_p50 = float(np.percentile(traj.effective_samples, 50))
        s.effective_samples_p10 = float(np.percentile(traj.effective_samples, 10))
    if traj.base_times.size:
        base = command_rates(traj.base_times, traj.base_commands)
        s.base_v_rate_mean, s.base_v_rate_p95 = mean_p95(base[:, 0])
        s.base_omega_rate_mean, s.base_omega_rate_p95 = mean_p95(base[:, 1])
        s.base_limited_fraction = float(np.mean([r == "limit" for r in traj.base_reasons]))
    if cfg.adapt_weights and terrain_names is not None:
        s.true_weight_mean = true_weight_mean(traj.times, traj.weights, traj.terrains, terrain_names)
        s.weight_switches_per_min = weight_switches_per_min(traj.times, traj.weights, identified=traj.identified)
        s.top_unidentified_share = unidentified_share(traj.times, traj.identified)
        s.unknown_share = unknown_share(traj.times, traj.unknown, traj.terrains, terrain_names)
        s.unknown_delay_s = unknown_delay_s(traj.times, traj.unknown, traj.terrains, terrain_names)
        s.unknown_new_share = unknown_share(traj.times, traj.unknown, traj.terrains, terrain_names, new_ground=True)
        if traj.unknown_active.size:
            s.unknown_active_share = float(np.mean(traj.unknown_active))
    for name, value in run_for(task).score(pos, traj.times, traj.status, cfg).items():
        setattr(s, name, value)
    return s


_WARM: set[str] = set()  # the planner settings and task types whose kernels this process has compiled or loaded


def warm_up(job: Job, settings: EvalSettings) -> None:
    """Compile or load the kernels of `job`'s planner before its runs, once per process, with an untimed plan of a
    planner of its own (with a delay, so the delay predictor is in too), as the planner service does before it goes
    live (`services.planner.warm_up`): a run's `planner_ms` is the deployed loop's time per step, not a compile's."""
    key = repr((settings, job.dynamics, job.terrain, type(job.scenario.task)))
    if key not in _WARM:
        planner = make_planner(settings, job.dynamics, job.terrain, job.seeds[0])
        try:
            planner.plan(job.scenario.start, job.scenario.task, delay_s=0.01)
        except (ValueError, FloatingPointError):
            pass  # the runs meet the same refusal and report it
        _WARM.add(key)


def run_job(job: Job, settings: EvalSettings) -> tuple[list[RunScore], list[Trajectory]]:
    """Run every seed of `job`; an infeasible scenario gives 'infeasible' scores instead of runs."""
    model = cached_gp_model(settings.gp_model)
    cfg = loop_config(settings, job)
    warm_up(job, settings)
    scores: list[RunScore] = []
    trajectories: list[Trajectory] = []
    estimator = None
    for seed in job.seeds:
        scenario = random_obstacle_scene(seed) if job.random_scenes else job.scenario
        problems = infeasibility(scenario, settings.robot_radius)
        if problems:
            scores.append(RunScore(seed=seed, status="infeasible", message="; ".join(problems)))
            continue
        planner = make_planner(settings, job.dynamics, job.terrain, seed)
        plant = make_plant(settings, job.terrain, seed)
        if cfg.adapt_weights:
            estimator = make_terrain_estimator(settings, plant)
        traj = run_closed_loop(
            planner,
            plant,
            scenario.task,
            scenario.start,
            model.n_terrains,
            cfg,
            estimator=estimator,
            initial_terrain=job.terrain,  # the plant starts on it already; this names it in the trajectory
            record_plans=False,
        )
        scores.append(score(traj, scenario.task, seed, cfg, list(model.terrains)))
        if job.record and not trajectories:
            trajectories.append(traj)
    return scores, trajectories


# per-trial scores a cell reports as their mean over trials and, as `<name>_std`, their population spread
SMOOTHNESS_AND_WEIGHT_METRICS = (
    "v_ref_rate_mean", "v_ref_rate_p95", "omega_ref_rate_mean", "omega_ref_rate_p95", "base_v_rate_mean",
    "base_v_rate_p95", "base_omega_rate_mean", "base_omega_rate_p95", "base_limited_fraction", "true_weight_mean",
    "weight_switches_per_min", "effective_samples_p50", "effective_samples_p10", "unknown_share",
    "unknown_active_share", "unknown_new_share", "top_unidentified_share",
)
# of those, the ones with no value (None, not nan) where no trial has one: a model without terrain weights
OPTIONAL_CELL_METRICS = ("true_weight_mean", "weight_switches_per_min", "unknown_share", "unknown_active_share",
                         "unknown_new_share", "top_unidentified_share")


def _mean_and_std(runs: list[RunScore], names: tuple[str, ...]) -> dict:
    out: dict = {}
    for name in names:
        values = [getattr(s, name) for s in runs if getattr(s, name) is not None]
        m, sd = mean_std(values)
        if name in OPTIONAL_CELL_METRICS and not values:
            m = sd = None
        out[name], out[f"{name}_std"] = m, sd
    return out


def summarize(scores: list[RunScore]) -> dict:
    """Aggregate one cell: mean RMSE, success count, time-to-goal mean and std over successes, etc."""
    runs = [s for s in scores if s.status != "infeasible"]
    rmse_m, rmse_s = mean_std([s.rmse_mm for s in runs])
    ttg_m, ttg_s = mean_std([s.time_to_goal_s for s in runs if s.success])
    ms = mean_std([s.planner_ms_mean for s in runs])[0]
    clear = [s.min_clearance_m for s in runs if np.isfinite(s.min_clearance_m)]
    finals = [s.final_weights for s in runs if s.final_weights]
    return {
        "rmse_mm": rmse_m,
        "rmse_std_mm": rmse_s,
        "success": int(sum(s.success for s in runs)),
        "trials": len(scores),
        "time_to_goal_s": ttg_m,
        "time_to_goal_std_s": ttg_s,
        "lane_exits": int(sum(s.lane_exits for s in runs)),
        "collisions": int(sum(s.status == "collision" for s in runs)),
        "min_clearance_m": float(min(clear)) if clear else float("nan"),
        "planner_ms": ms,
        "mean_speed_mps": mean_std([s.mean_speed_mps for s in runs])[0],
        "infeasible": len(scores) - len(runs),
        "final_weights_mean": [float(x) for x in np.mean(finals, axis=0)] if finals else [],
        # the slowest detection of new ground over the trials (None: no trial reached one)
        "unknown_delay_max_s": max(d) if (d := [s.unknown_delay_s for s in runs if s.unknown_delay_s is not None])
        else None,
        **_mean_and_std(runs, SMOOTHNESS_AND_WEIGHT_METRICS),
        "statuses": {st: sum(s.status == st for s in scores) for st in sorted({s.status for s in scores})},
    }


def score_dicts(scores: list[RunScore]) -> list[dict]:
    return [asdict(s) for s in scores]


def figure_record(traj: Trajectory) -> dict:
    """The small part of a trajectory the figures need: the driven XY, typical inflated radii, the cycles' start times
    with the terrain weights and the planner's commands."""
    rec: dict = {"xy": traj.positions.copy(), "inflated": None, "times": traj.times[:-1].copy(),
                 "weights": traj.weights.copy(), "weights_ok": traj.weights_ok.copy(),
                 "commands": traj.commands.copy()}
    goal_tight = [t for t in traj.tightened if t.ndim == 2 and t.shape[1] > 0]
    if goal_tight:
        # per obstacle: the largest inflation along each plan's horizon, median over the run's cycles
        rec["inflated"] = np.median(np.stack([t.max(axis=0) for t in goal_tight]), axis=0)
    return rec


def run_job_for_report(job: Job, settings: EvalSettings) -> tuple[Job, list[RunScore], dict | None]:
    """Worker entry point: scores of every seed, and the first seed's figure record if `job.record`."""
    scores, trajectories = run_job(job, settings)
    return job, scores, (figure_record(trajectories[0]) if trajectories else None)


def init_worker(threads: int) -> None:
    """Worker initializer: share the cores between workers instead of oversubscribing them."""
    import numba

    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    try:
        import torch

        torch.set_num_threads(max(1, threads))
    except ImportError:
        pass
