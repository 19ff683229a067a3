"""`gpmppi warm`: compile the numba kernels that the shipped configurations compile at start, once, into the
kernel cache, so that a later `gpmppi demo` / `gpmppi launch` (and `gpmppi evaluate`) starts in seconds.

What is compiled is what each service does before it goes live, with the settings the shipped launch files give
it: the planner (`services.planner`: build the planner and plan its first seconds from the scenario's start,
`Planner.warm_up`: with a small delay, so the delay predictor is compiled too, and on new terrain weights, so the
table's collapse is) for every distinct planner entry of the shipped launch files, on the lane
and on the goal task (a task message can switch a running planner to either); the EDD5 and unicycle baselines
the evaluation runs; the simulated plant (`services.sim`: one step); and the terrain estimator (`services.terrain`:
a few transitions and one solve). numba keys its cache on the source files, so this warms the cache of this
checkout (the folder `gpmppi/__init__.py` chooses); with a warm cache it takes only the time to load.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import typer

REPO = Path(__file__).resolve().parents[1]
SHIPPED_LAUNCH_FILES = [REPO / "services" / "launch" / "default.yaml", *sorted((REPO / "deploy").glob("*.yaml"))]
GOAL_SCENARIO = "paper_obstacles"
EVALUATION_DYNAMICS = ("edd5", "unicycle")


def shipped_planner_configs() -> Iterator[tuple[str, dict]]:
    """(launch file name, planner entry's config) for every enabled planner entry of the shipped launch files."""
    from services.launch.launch_file import LaunchFile

    for path in SHIPPED_LAUNCH_FILES:
        launch = LaunchFile.load(path)
        for entry in launch.services:
            if entry.enabled and (entry.kind or entry.name) == "planner":
                yield path.name, entry.config


def _warm_planners(log: Callable[[str], None]) -> None:
    from gpmppi.mppi import kernel_cache
    from gpmppi.mppi.config import PlannerConfig
    from gpmppi.mppi.planner import Planner
    from services.planner import Settings, load_model, warm_up_scenario

    # (planner settings, model file, scenario) -> where it comes from; each distinct one planned once
    runs: dict[tuple[str, str | None, str], str] = {}
    for source, config in shipped_planner_configs():
        settings = Settings(**config)
        for scenario in dict.fromkeys([settings.scenario, GOAL_SCENARIO]):
            key = (settings.planner.model_dump_json(), settings.model_file, scenario)
            runs.setdefault(key, f"{source}: planner on {scenario}")
    default = Settings()
    for dynamics in EVALUATION_DYNAMICS:
        planner = default.planner.model_copy(update={"dynamics": dynamics})
        runs.setdefault((planner.model_dump_json(), None, "circle"), f"evaluation: {dynamics} on circle")
    models = {}
    for (planner_json, model_file, scenario_name), what in runs.items():
        t = time.perf_counter()
        if model_file not in models:
            models[model_file] = load_model(model_file)
        scenario = warm_up_scenario(scenario_name)
        planner = Planner(PlannerConfig.model_validate_json(planner_json), models[model_file])
        c = planner.config
        # as the planner service warms up before going live (`Planner.warm_up`: the plans of its first seconds), through
        # the same call, which records the kernels so that the service finds them cached
        kernel_cache.warm_up(
            kernel_cache.planner_label(c.dynamics, c.gp_mode, planner.backend),
            lambda p=planner, s=scenario: p.warm_up(np.asarray(s.start, dtype=np.float64), s.task),
            lambda line: None,
        )
        log(f"  {what}: {time.perf_counter() - t:.1f} s")


def _warm_sim(log: Callable[[str], None]) -> None:
    from gpmppi.plant.physics import PhysicsPlant
    from gpmppi.plant.terrains import load_terrains
    from services.sim import Settings, initial_state

    t = time.perf_counter()
    settings = Settings()
    plant = PhysicsPlant(load_terrains(settings.terrain_file), settings.terrain, seed=settings.seed,
                         noise=settings.noise)
    plant.reset(initial_state(settings))
    plant.step(np.array([1.0, 0.2]), 1.0 / settings.step_hz)
    plant.measure()
    log(f"  sim plant: {time.perf_counter() - t:.1f} s")


def _warm_terrain(log: Callable[[str], None]) -> None:
    from gpmppi.gp.model_file import GPModel, load_default_model
    from gpmppi.terrain.estimator import make_estimator
    from services.terrain import Settings

    t = time.perf_counter()
    settings = Settings()
    model = load_default_model() if settings.model_file is None else GPModel.load(settings.model_file)
    estimator = make_estimator(model, settings.estimator)
    x = np.array([0.0, 0.0, 0.0, 1.0, 0.1])
    for k in range(estimator.min_history + 1):
        nxt = x + np.array([0.1, 0.0, 0.01, 0.01 * (k % 2), 0.0])
        estimator.observe(x, np.array([1.0, 0.1]), nxt)
        x = nxt
    estimator.estimate()
    log(f"  terrain estimator: {time.perf_counter() - t:.1f} s")


def warm(log: Callable[[str], None] = print) -> float:
    """Compile (or load) every kernel the shipped configurations use; returns the seconds it took."""
    t = time.perf_counter()
    _warm_planners(log)
    _warm_sim(log)
    _warm_terrain(log)
    return time.perf_counter() - t


def register(app: typer.Typer) -> None:
    """Add `gpmppi warm`."""

    @app.command("warm")
    def warm_cmd() -> None:
        """Compile the planner, plant and terrain kernels of the shipped configurations into the kernel cache
        (deploy/setup.sh runs it), so that services start without compiling."""
        import os

        import gpmppi  # noqa: F401 - chooses the kernel cache folder (NUMBA_CACHE_DIR) before numba is imported

        typer.echo(f"kernel cache: {os.environ.get('NUMBA_CACHE_DIR')}")
        typer.echo(f"warm in {warm(typer.echo):.1f} s")
