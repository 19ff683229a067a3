"""`python -m tools.profile_loop`: where a closed loop's planner time per step goes, model by model.

Runs the quick table's cells (`gpmppi evaluate table --quick`: physics plant, the shipped launch file's command path,
the first terrain, lanes 25 m with seed 0, the obstacle scene with seeds 0-4) in this process, and splits each
step's `planner_ms` (the wall time of `PlannerCycle.on_state`, what the table reports) into the plan's own phases
(`PlanResult.timings_ms`), the parts of those phases (the covariance propagation, the task kind's bounds, the
per-critic nominal scorer), what `Planner.plan` does outside its phases, and what the cycle adds around the plan.
The first cell is run once untimed first (numba's compile or cache load, the lane lookup's build), so no compile
is counted; `--cold` reports the first step of the first cell as the table's first cell sees it.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections import defaultdict
from collections.abc import Callable

import numpy as np

from gpmppi.evaluation.closed_loop import run_closed_loop
from gpmppi.evaluation.runner import (
    EvalSettings,
    Job,
    cached_gp_model,
    loop_config,
    make_planner,
    make_plant,
    make_terrain_estimator,
)
from gpmppi.mppi import backends


def quick_settings() -> EvalSettings:
    """The settings `gpmppi evaluate table --quick` runs with (defaults otherwise)."""
    from tools.evaluate import _settings
    from tools.evaluate_options import PlantName

    return _settings(PlantName.physics, None, None, None, 1024, None, True, 0.0, 0, True, True, None)


class _Timer:
    """Sums of wall time [ms] by name, for the current plan and over all plans."""

    def __init__(self) -> None:
        self.plan: dict[str, float] = defaultdict(float)

    def wrap(self, name: str, fn: Callable) -> Callable:
        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.plan[name] += (time.perf_counter() - t0) * 1e3
        return timed


def run_cell(job: Job, settings: EvalSettings) -> dict[str, list[float]]:
    """Every step of every seed of `job`: per-step values [ms] by name."""
    model = cached_gp_model(settings.gp_model)
    cfg = loop_config(settings, job)
    rows: dict[str, list[float]] = defaultdict(list)
    timer = _Timer()
    real_critic_costs = backends.critic_costs
    backends.critic_costs = timer.wrap("critic_costs", real_critic_costs)
    try:
        for seed in job.seeds:
            planner = make_planner(settings, job.dynamics, job.terrain, seed)
            planner._propagate = timer.wrap("propagate", planner._propagate)
            kind = planner.kind(job.scenario.task)
            kind.bounds = timer.wrap("bounds", kind.bounds)
            real_plan = planner.plan

            def plan(*args, _real=real_plan, **kwargs):
                timer.plan.clear()
                t0 = time.perf_counter()
                result = _real(*args, **kwargs)
                wall = (time.perf_counter() - t0) * 1e3
                t = result.timings_ms
                rows["plan_wall"].append(wall)
                for name in ("total", "collapse", "tighten", "rollouts", "update", "nominal"):
                    rows[name].append(t[name])
                rows["plan_other"].append(t["total"] - sum(t[n] for n in ("collapse", "tighten", "rollouts", "update",
                                                                        "nominal")))
                for name in ("propagate", "bounds", "critic_costs"):
                    rows[name].append(timer.plan.get(name, 0.0))
                return result

            planner.plan = plan
            plant = make_plant(settings, job.terrain, seed)
            estimator = make_terrain_estimator(settings, plant) if cfg.adapt_weights else None
            traj = run_closed_loop(planner, plant, job.scenario.task, job.scenario.start, model.n_terrains, cfg,
                                   estimator=estimator, initial_terrain=job.terrain)
            rows["planner_ms"].extend(traj.planner_ms.tolist())
            rows["seed_mean"].append(float(np.mean(traj.planner_ms)))
            rows["first_step"].append(float(traj.planner_ms[0]))
            rows["later_steps"].extend(traj.planner_ms[1:].tolist())
    finally:
        backends.critic_costs = real_critic_costs
    n = len(rows["planner_ms"])
    rows["cycle_other"] = list(np.asarray(rows["planner_ms"]) - np.asarray(rows["plan_wall"][:n]))
    return rows


COLUMNS = ("planner_ms", "first_step", "later_steps", "total", "collapse", "tighten", "rollouts", "update", "nominal",
           "plan_other", "cycle_other", "propagate", "bounds", "critic_costs")


def main() -> None:
    from tools.evaluate_jobs import load_lanes, load_scenes

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="gp,unicycle", help="comma-separated models")
    ap.add_argument("--cells", default="square,avoidance", help="comma-separated cells (circle, square, avoidance)")
    ap.add_argument("--rounds", type=int, default=1, help="times each cell is run (interleaved by model)")
    ap.add_argument("--cold", action="store_true", help="no untimed warm-up: report the first step's time")
    ap.add_argument("--oracle", action="store_true",
                    help="the GP gets the true terrain's one-hot weights (fixed: no collapse in the rollouts)")
    args = ap.parse_args()
    settings = dataclasses.replace(quick_settings(), oracle_weights=args.oracle)
    terrain = "asphalt"
    scenarios = {**load_lanes(None), **load_scenes(None)}
    models = args.models.split(",")
    cells = args.cells.split(",")

    def job(label: str, model: str) -> Job:
        kind = "avoidance" if label == "avoidance" else "tracking"
        seeds = tuple(range(5)) if kind == "avoidance" else (0,)
        return Job(kind, scenarios[label], terrain, model, seeds, label=label)  # type: ignore[arg-type]

    if args.cold:
        t0 = time.perf_counter()
        rows = run_cell(job(cells[0], models[0]), settings)
        print(f"cold: {cells[0]} {models[0]}: first step {rows['planner_ms'][0]:.1f} ms, steps "
              f"{len(rows['planner_ms'])}, mean {np.mean(rows['planner_ms']):.2f} ms, mean without the first "
              f"{np.mean(rows['planner_ms'][1:]):.2f} ms ({time.perf_counter() - t0:.1f} s)")
    else:
        for label in cells:  # compile or load every model's kernels for every task kind untimed
            for m in models:
                run_cell(job(label, m), settings)
    print("cell model steps | " + " ".join(f"{c:>12s}" for c in COLUMNS) + " | per-seed means")
    means: dict[tuple[str, str], list[list[float]]] = defaultdict(list)
    for r in range(args.rounds):
        for label in cells:
            for m in models:
                rows = run_cell(job(label, m), settings)
                means[label, m].append([float(np.mean(rows[c])) for c in COLUMNS])
                seeds = " ".join(f"{v:.2f}" for v in rows["seed_mean"])
                print(f"{r} {label} {m} {len(rows['planner_ms'])} | "
                      + " ".join(f"{v:12.3f}" for v in means[label, m][-1]) + f" | {seeds}", flush=True)
    print("median over rounds of each round's mean [ms]")
    for (label, m), values in means.items():
        print(f"{label} {m} | " + " ".join(f"{v:12.3f}" for v in np.median(values, axis=0)))


if __name__ == "__main__":
    main()
