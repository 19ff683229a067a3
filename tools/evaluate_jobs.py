"""The closed-loop runs of `gpmppi evaluate`: the scenarios (the shipped lanes and scene, or files), the jobs of a
grid of tasks x terrains x models x seeds, and running them (here, in spawned workers or on a Ray cluster) into
the summarised results. The command's options, checks and printing are `tools.evaluate`."""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from gpmppi.evaluation.runner import EvalSettings, Job, init_worker, run_job_for_report, summarize
from gpmppi.scenarios import (
    Scenario,
    ScenarioFileError,
    circle_lane,
    load_lane,
    load_scene,
    paper_obstacle_scene,
    square_lane,
)
from tools.cli_checks import fail


def load_lanes(lane_files: list[Path] | None) -> dict[str, Scenario]:
    if not lane_files:
        return {"circle": circle_lane(), "square": square_lane()}
    try:
        return {f.stem: load_lane(f) for f in lane_files}
    except ScenarioFileError as e:
        fail(str(e))
    raise AssertionError


def load_scenes(scene_files: list[Path] | None) -> dict[str, Scenario]:
    if not scene_files:
        return {"avoidance": paper_obstacle_scene()}
    try:
        return {("avoidance" if len(scene_files) == 1 else f.stem): load_scene(f) for f in scene_files}
    except ScenarioFileError as e:
        fail(str(e))
    raise AssertionError


def make_jobs(
    lanes: dict[str, Scenario], scenes: dict[str, Scenario], terrains: list[str], models: list[str],
    lane_trials: int, goal_trials: int, seed: int, switches: tuple, random_scenes: bool, chunk: int = 10,
) -> list[Job]:
    jobs: list[Job] = []
    for label, sc in lanes.items():
        for terrain in terrains:
            for m in models:
                seeds = tuple(range(seed, seed + lane_trials))
                jobs.append(Job("tracking", sc, terrain, m, seeds, True, switches, label))  # type: ignore[arg-type]
    for label, sc in scenes.items():
        for terrain in terrains:
            for m in models:
                for i in range(0, goal_trials, chunk):
                    seeds = tuple(range(seed + i, seed + min(goal_trials, i + chunk)))
                    jobs.append(
                        Job("avoidance", sc, terrain, m, seeds, i == 0, switches, label, random_scenes)  # type: ignore[arg-type]
                    )
    return jobs


def execute_jobs(
    jobs: list[Job], settings: EvalSettings, workers: int, quiet: bool, ray_address: str | None = None,
) -> tuple[dict, dict, float]:
    """Run all jobs: on a Ray cluster (`ray_address`), in spawn workers (workers > 1) or here; results[task][terrain]
    [model], figure paths, seconds."""
    scores: dict = {}
    paths: dict = {}
    total = sum(len(j.seeds) for j in jobs)
    console = Console(stderr=True, quiet=quiet)
    t0 = time.perf_counter()
    ray = None
    if ray_address is not None:
        from tools.evaluate_ray import RayBackendError, connect

        try:
            ray = connect(ray_address)
        except RayBackendError as e:
            fail(str(e))
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TimeRemainingColumn())
    with Progress(*columns, console=console, transient=False) as progress:
        bar = progress.add_task("closed-loop runs", total=total)

        def collect(job: Job, job_scores: list, record: dict | None) -> None:
            scores.setdefault(job.label, {}).setdefault(job.terrain, {}).setdefault(job.dynamics, []).extend(job_scores)
            if record is not None:
                paths.setdefault(job.label, {}).setdefault(job.terrain, {})[job.dynamics] = record
            progress.update(bar, advance=len(job.seeds), description=f"{job.label} {job.terrain} {job.dynamics}")

        if ray is not None:
            from tools.evaluate_ray import run_jobs

            try:
                for result in run_jobs(ray, jobs, settings):
                    collect(*result)
            finally:
                ray.shutdown()  # disconnects this driver; the cluster keeps running
        elif workers == 1:
            for job in jobs:
                collect(*run_job_for_report(job, settings))
        else:
            threads = max(1, (os.cpu_count() or 2) // workers)
            ctx = mp.get_context("spawn")
            with ProcessPoolExecutor(workers, mp_context=ctx, initializer=init_worker, initargs=(threads,)) as pool:
                # long lane jobs first, so the pool does not end on one long straggler
                ordered = sorted(jobs, key=lambda j: j.kind != "tracking")
                futures = [pool.submit(run_job_for_report, job, settings) for job in ordered]
                for fut in as_completed(futures):
                    collect(*fut.result())
    # cells in the order the jobs were listed (tasks, terrains, models), not in completion order
    order = {}
    for j in jobs:
        order.setdefault(j.label, {}).setdefault(j.terrain, {}).setdefault(j.dynamics, None)
    results = {
        task: {t: {m: summarize(scores[task][t][m]) for m in by_m} for t, by_m in by_t.items()}
        for task, by_t in order.items()
    }
    return results, paths, time.perf_counter() - t0
