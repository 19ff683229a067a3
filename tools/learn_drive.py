"""`gpmppi evaluate learn-ground`: drive GP-MPPI on a ground for a while, learn it online as the terrain service does,
and write the learned profile (the measurement of docs/new_ground.md, "Learning a new ground").

The closed loop is the evaluation's (the deployed command path: egress's limits, the terrain service's cycle); its
terrain estimator is wrapped in a `TeeEstimator`, so the learner gets exactly the steps the terrain service would
collect, and the fit is the service's (`run_fit`: `learn_ground`, then the atomic save).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Literal

import typer

from tools.cli_checks import OUT_FILE, fail


def learn_on_ground(
    ground: str, seconds: float, output: Path, name: str, profile: Path | None, scenario: str, seed: int,
    hyperparameters: Literal["kept", "fitted"], samples: int,
) -> str:
    """Drive, learn, save; the report line."""
    from gpmppi.evaluation.closed_loop import ClosedLoopConfig, run_closed_loop
    from gpmppi.evaluation.runner import (
        EvalSettings,
        cached_gp_model,
        cached_terrain_set,
        make_planner,
        make_plant,
        make_terrain_estimator,
    )
    from gpmppi.scenarios import circle_lane, square_lane
    from gpmppi.terrain.learning import GroundLearning, LearnConfig, TeeEstimator
    from services.terrain_learning import run_fit

    settings = EvalSettings(gp_model=None if profile is None else str(profile), samples=samples)
    grounds = sorted(cached_terrain_set(None).terrains)
    if ground not in grounds:
        fail(f"--terrain {ground!r}: not a ground of the plant's terrain set {grounds}")
    model = cached_gp_model(settings.gp_model)
    sc = circle_lane() if scenario == "circle" else square_lane()
    plant = make_plant(settings, ground, seed)
    steps = int(round(seconds / model.dt)) - 2  # the first and last states pair with nothing
    learning = GroundLearning(model, LearnConfig(steps=max(10, steps), min_samples=min(300, max(10, steps)),
                                                 hyperparameters=hyperparameters, seed=seed))
    learning.start(name)
    estimator = TeeEstimator(make_terrain_estimator(settings, plant), learning)
    cfg = ClosedLoopConfig(time_limit_s=seconds, safety=settings.safety, terrain=settings.terrain_cycle)
    run_closed_loop(make_planner(settings, "gp", ground, seed), plant, sc.task, sc.start, model.n_terrains, cfg,
                    estimator=estimator, initial_terrain=ground)
    job = learning.take_job()
    if job is None:
        n = 0 if learning.samples is None else len(learning.samples)
        fail(f"{n} steps collected on {ground} in {seconds} s, {learning.config.steps} needed; drive longer")
    t = time.perf_counter()
    out = run_fit(job, str(output))
    if out.error:
        fail(out.error)
    return f"{out.message}; fit and save {time.perf_counter() - t:.1f} s; saved to {output} (sha256 {out.sha256})"


def register(app: typer.Typer) -> None:
    @app.command("learn-ground")
    def learn_ground_cmd(
        output: Annotated[Path, typer.Option("-o", "--output", metavar=OUT_FILE, help="the learned profile (.npz)")],
        terrain: Annotated[str, typer.Option("-t", "--terrain", help="the plant's ground to drive on (e.g. sand, "
                                            "held out of the shipped profile)")] = "sand",
        seconds: Annotated[float, typer.Option(min=2.0, help="seconds of driving on it before the fit")] = 60.0,
        name: Annotated[str, typer.Option(help="the learned ground's name ('' : new-1)")] = "",
        profile: Annotated[Path | None, typer.Option(help="the robot profile to extend (default: shipped)")] = None,
        scenario: Annotated[str, typer.Option(help="circle or square lane")] = "circle",
        seed: Annotated[int, typer.Option(min=0, help="seed of the plant and the planner")] = 0,
        hyperparameters: Annotated[str, typer.Option(help="kept or fitted (gpmppi/gp/online_ground.py)")] = "kept",
        samples: Annotated[int, typer.Option(min=16, help="MPPI samples")] = 1024,
    ) -> None:
        """Drive GP-MPPI on a ground, learn it online as the terrain service does, write the learned profile."""
        if scenario not in ("circle", "square"):
            fail(f"--scenario {scenario!r}: choose circle or square")
        if hyperparameters not in ("kept", "fitted"):
            fail(f"--hyperparameters {hyperparameters!r}: choose kept or fitted")
        print(learn_on_ground(terrain, seconds, output, name, profile, scenario, seed, hyperparameters,  # type: ignore[arg-type]
                              samples))
