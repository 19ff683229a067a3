"""`gpmppi evaluate tracking|avoidance|table`: closed-loop evaluation, the paper's Table 1 and figures."""

from __future__ import annotations

import json
import math
import shlex
import sys
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from gpmppi.evaluation.runner import MODELS, PAPER_NET_TERRAINS, EvalSettings
from gpmppi.scenarios import Scenario
from tools import learn_drive, terrain_cmd, terrain_separability
from tools.choices import ModelName
from tools.cli_checks import check_output_dir, fail, only_with
from tools.evaluate_jobs import execute_jobs, load_lanes, load_scenes, make_jobs
from tools.evaluate_options import (
    CompensateOpt,
    DeployOpt,
    DistanceOpt,
    EstimatorOpt,
    ForceOpt,
    JsonOpt,
    LaneFileOpt,
    LatencyCyclesOpt,
    LatencyOpt,
    ModelOpt,
    NoiseOpt,
    OracleOpt,
    OutOpt,
    PlantFileOpt,
    PlantName,
    PlantOpt,
    ProfileOpt,
    QuickOpt,
    RandomOpt,
    RayOpt,
    SamplesOpt,
    SceneFileOpt,
    SeedOpt,
    SetOpt,
    SwitchOpt,
    TerrainFileOpt,
    TerrainOpt,
    TrialsOpt,
    WorkersOpt,
    parse_overrides,
    parse_switches,
)
from tools.real_data_cmd import real_data_cmd


def _default_terrains(settings: EvalSettings) -> list[str]:
    if settings.plant == "residual-net":
        return list(PAPER_NET_TERRAINS)
    from gpmppi.evaluation.runner import cached_gp_model

    return list(cached_gp_model(settings.gp_model).terrains)


def _check_profile_grounds(profile: Path, grounds: list[str], terrain_file: Path | None) -> None:
    """One line when the profile has a ground the physics plant's terrain set lacks (a profile of another robot)."""
    from gpmppi.plant.terrains import TerrainFileError, load_terrains

    try:
        names = load_terrains(terrain_file).names
    except TerrainFileError as e:
        fail(str(e))
    missing = [g for g in grounds if g not in names]
    if missing:
        where = f"--terrain-file {terrain_file}" if terrain_file else "the shipped terrain set (no --terrain-file)"
        fail(f"profile {profile}: ground {missing[0]!r} of the profile (its grounds: {grounds}) is not in "
             f"{where}, which has {list(names)}; pass the --terrain-file of the profile's robot")


def _check_terrains(settings: EvalSettings, terrains: list[str]) -> None:
    if settings.plant == "residual-net":
        bad = [t for t in terrains if t not in PAPER_NET_TERRAINS]
        if bad:
            fail(f"the residual-net plant knows terrains {PAPER_NET_TERRAINS}, not {bad}")
        return
    from gpmppi.plant.terrains import TerrainFileError, load_terrains

    try:
        names = load_terrains(settings.terrain_file).names
    except TerrainFileError as e:
        fail(str(e))
    bad = [t for t in terrains if t not in names]
    if bad:
        fail(f"unknown terrain(s) {bad}; the terrain set has {names} (see --terrain-file)")


def _check_applies(
    kind: str, scene_file: list[Path] | None, lane_file: list[Path] | None, random_scenes: bool,
    distance: float | None,
) -> None:
    """An option the chosen command would ignore is an error: the user believes their file was evaluated."""
    lanes_only = {"--lane-file": bool(lane_file), "--distance": distance is not None}
    scenes_only = {"--scene-file": bool(scene_file), "--random-scenes": random_scenes}
    ignored = [o for o, on in lanes_only.items() if on] if kind == "avoidance" else []
    ignored += [o for o, on in scenes_only.items() if on] if kind == "tracking" else []
    if ignored:
        other = "tracking" if kind == "avoidance" else "avoidance"
        fail(f"{', '.join(ignored)}: does not apply to `evaluate {kind}`; use `evaluate {other}` or `evaluate table`")


def _settings(
    plant: PlantName, plant_file: Path | None, terrain_file: Path | None, gp_model: Path | None, samples: int,
    distance: float | None, quick: bool, latency: float, latency_cycles: int, compensate: bool, noise: bool,
    overrides: list[str] | None, estimator: list[str] | None = None, oracle: bool = False,
    deploy: Path | None = None,
) -> EvalSettings:
    only_with(plant is PlantName.residual_net, "--plant residual-net", {"--plant-file": plant_file is not None})
    if plant is PlantName.residual_net and plant_file is None:
        fail("--plant residual-net needs --plant-file (the network JSON, e.g. fcnn.json)")
    # the deployed command path: egress's limits, the terrain service's cycle and estimator of the launch file, and
    # its robot profile unless --profile names one
    from gpmppi.evaluation.deployed import DeployFileError, deployed_path
    from services.launch.launch_file import DEFAULT_LAUNCH

    try:
        deployed = deployed_path(deploy or DEFAULT_LAUNCH)
    except DeployFileError as e:
        fail(f"--launch-file: {e}")
    profile_label = "--profile"
    if gp_model is None and deployed.profile is not None:
        gp_model, profile_label = Path(deployed.profile), f"--launch-file {deployed.source}: profile"
    for label, f in (("--plant-file", plant_file), ("--terrain-file", terrain_file), (profile_label, gp_model)):
        if f is not None and not f.is_file():
            fail(f"{label} {f}: file not found")
    if plant_file is not None:
        from gpmppi.plant.residual_net import NetworkFileError, load_residual_net

        try:
            load_residual_net(plant_file)  # here, not first in a worker after the pool has started
        except NetworkFileError as e:
            fail(f"--plant-file: {e}")
    if gp_model is not None:
        from gpmppi.evaluation.runner import cached_gp_model
        from gpmppi.gp.model_file import ModelFileError

        try:
            grounds = list(cached_gp_model(str(gp_model)).terrains)
        except (ModelFileError, OSError) as e:
            fail(f"{profile_label}: {e}")
        if plant is PlantName.physics:
            _check_profile_grounds(gp_model, grounds, terrain_file)
    lane_m = distance if distance is not None else (25.0 if quick else 100.0)
    planner_overrides = parse_overrides(overrides)
    try:
        estimator_fields = terrain_cmd.estimator_settings(estimator or [])
    except ValueError as e:
        fail(f"--estimator: {e}")
    estimator_fields = (*deployed.estimator.model_dump(exclude_unset=True).items(), *estimator_fields)
    return EvalSettings(
        plant=plant.value,  # type: ignore[arg-type]
        plant_file=str(plant_file) if plant_file else None,
        terrain_file=str(terrain_file) if terrain_file else None,
        gp_model=str(gp_model) if gp_model else None,
        samples=samples,
        lane_distance_m=lane_m,
        latency_s=latency + latency_cycles * 0.1,
        compensate_latency=compensate,
        sensor_noise=noise,
        planner_overrides=planner_overrides,
        terrain_estimator=estimator_fields,
        oracle_weights=oracle,
        safety=deployed.safety,
        terrain_cycle=deployed.terrain,
    )


def _print_results(results: dict) -> None:
    table = Table(title="closed-loop evaluation")
    for col in ("task", "terrain", "model", "RMSE [mm]", "success", "time-to-goal [s]", "lane exits", "planner [ms]"):
        table.add_column(col)
    for task, by_t in results.items():
        for terrain, by_m in by_t.items():
            for m, c in by_m.items():
                ttg = c["time_to_goal_s"]
                table.add_row(
                    task, terrain, m,
                    "-" if math.isnan(c["rmse_mm"]) else f"{c['rmse_mm']:.1f}",
                    f"{c['success']}/{c['trials']}",
                    "-" if math.isnan(ttg) else f"{ttg:.2f} ± {c['time_to_goal_std_s']:.2f}",
                    str(c["lane_exits"]),
                    "-" if math.isnan(c["planner_ms"]) else f"{c['planner_ms']:.1f}",
                )
    Console(width=max(Console().width, 110)).print(table)


def _finish(
    results: dict, paths: dict, scenarios: dict[str, Scenario], seconds: float, settings: EvalSettings,
    terrains: list[str], models: list[str], out: Path | None, as_json: bool,
) -> None:
    meta = {
        "command": "gpmppi " + " ".join(shlex.quote(a) for a in sys.argv[1:]),
        "wall_time_s": round(seconds, 1),
        # the deployed path's settings (pydantic models) as plain data
        "settings": {k: v.model_dump() if hasattr(v, "model_dump") else v for k, v in settings.__dict__.items()},
        "terrains": terrains,
        "models": models,
    }
    if out is not None:
        from tools.report import write_figures, write_tables

        written = write_tables(results, meta, out, models, terrains)
        from gpmppi.evaluation.runner import cached_gp_model

        written += write_figures(paths, scenarios, results, out, list(cached_gp_model(settings.gp_model).terrains))
        Console(stderr=True).print(f"wrote {', '.join(str(p) for p in written)}")
    if as_json:
        print(json.dumps({"results": results, "meta": meta}, default=float))
    else:
        _print_results(results)
        Console().print(f"wall time {seconds:.1f} s")


def _run(
    kind: str, terrain: list[str] | None, model: list[ModelName] | None, trials: int | None, seed: int,
    plant: PlantName, plant_file: Path | None, terrain_file: Path | None, scene_file: list[Path] | None,
    lane_file: list[Path] | None, gp_model: Path | None, quick: bool, as_json: bool, out: Path | None,
    workers: int, samples: int, distance: float | None, latency: float, latency_cycles: int, compensate: bool,
    noise: bool, random_scenes: bool, switch: list[str] | None, overrides: list[str] | None,
    estimator: list[str] | None = None, oracle: bool = False, ray_address: str | None = None,
    deploy: Path | None = None, force: bool = False,
) -> None:
    _check_applies(kind, scene_file, lane_file, random_scenes, distance)
    if out is not None and out.is_dir() and any(out.iterdir()) and not force:
        fail(f"--output {out}: the folder holds files already; choose an empty or new folder, or add --force to "
             "write over its tables and figures")
    settings = _settings(plant, plant_file, terrain_file, gp_model, samples, distance, quick, latency,
                         latency_cycles, compensate, noise, overrides, estimator, oracle, deploy)
    terrains = terrain or _default_terrains(settings)
    if quick and not terrain:
        terrains = terrains[:1]
    _check_terrains(settings, terrains + [name for _, name in parse_switches(switch)])
    models = [m.value for m in model] if model else list(MODELS)
    lanes = load_lanes(lane_file) if kind in ("tracking", "table") else {}
    scenes = load_scenes(scene_file) if kind in ("avoidance", "table") else {}
    goal_trials = trials or (5 if quick else 100)
    # one lane run's RMSE moves by several mm with the seed (a corner taken a little differently): the table
    # reports the mean of three
    lane_trials = trials if (trials and kind == "tracking") else (1 if quick else 3)
    jobs = make_jobs(lanes, scenes, terrains, models, lane_trials, goal_trials, seed, parse_switches(switch),
                 random_scenes)
    results, paths, seconds = execute_jobs(jobs, settings, workers, quiet=False, ray_address=ray_address)
    _finish(results, paths, {**lanes, **scenes}, seconds, settings, terrains, models, out, as_json)


def register(app: typer.Typer) -> None:
    """Add `gpmppi evaluate ...`."""
    ev = typer.Typer(help="Closed-loop evaluation: lanes, obstacle scenes, the paper's Table 1.", no_args_is_help=True)

    def make(kind: str, doc: str):
        def command(
            terrain: TerrainOpt = None, model: ModelOpt = None, trials: TrialsOpt = None, seed: SeedOpt = 0,
            plant: PlantOpt = PlantName.physics, plant_file: PlantFileOpt = None, terrain_file: TerrainFileOpt = None,
            scene_file: SceneFileOpt = None, lane_file: LaneFileOpt = None, gp_model: ProfileOpt = None,
            quick: QuickOpt = False, as_json: JsonOpt = False, out: OutOpt = None, workers: WorkersOpt = 2,
            samples: SamplesOpt = 1024, distance: DistanceOpt = None, latency: LatencyOpt = 0.0,
            latency_cycles: LatencyCyclesOpt = 0, compensate: CompensateOpt = True, noise: NoiseOpt = True,
            random_scenes: RandomOpt = False, switch: SwitchOpt = None, set_: SetOpt = None,
            estimator: EstimatorOpt = None, oracle: OracleOpt = False, ray: RayOpt = None,
            deploy: DeployOpt = None, force: ForceOpt = False,
        ) -> None:
            if kind == "table" and out is None:
                out = Path("evaluation")
                check_output_dir("--output", out)
            _run(kind, terrain, model, trials, seed, plant, plant_file, terrain_file, scene_file, lane_file,
                 gp_model, quick, as_json, out, workers, samples, distance, latency, latency_cycles, compensate,
                 noise, random_scenes, switch, set_, estimator, oracle, ray, deploy, force)

        command.__doc__ = doc
        return command

    ev.command("tracking")(make("tracking", "Lane tracking (circle and square, or --lane-file): RMSE, lane exits."))
    ev.command("avoidance")(make("avoidance", "Obstacle avoidance (the paper's scene or --scene-file): success."))
    ev.command("table")(make("table", "The whole grid (terrains x models x {circle, square, avoidance}) into -o DIR."))
    terrain_cmd.register(ev)
    terrain_separability.register(ev)
    learn_drive.register(ev)
    ev.command("terrain-real-data")(real_data_cmd)
    app.add_typer(ev, name="evaluate")
