"""`python -m tools.profile_lookup`: what the GP table's lookups cost the rollouts, in the closed loop and in the bench,
with the caches as each plan met them and again at once with the caches warm.

Every plan's rollout kernel call is replaced, in turn, by one of two measures (both give the kernel's results, so the
runs go on as they would):
- `kernel`: the real kernel (on the planner's threads) timed as the plan meets the caches ("cold"), then run again at
  once over the same inputs ("warm"): cold - warm is what the caches cost (and, with moving weights, the slabs the
  plan collapsed, which the second run finds current);
- `phases`: `tools.profile_planner`'s copy of the worker with the cycle counter around each phase, on one thread, cold
  then warm; the cold run records every lookup's five table rows, whose 64-byte lines are counted: the lines of one
  plan, those the plan before touched too, and the lines a lookup's rows fall in.

Cells: the quick table's square (seed 0) and obstacle scene (seeds 0-4), GP and unicycle, through
`tools.profile_loop.run_cell` (the closed loop as `gpmppi evaluate table --quick` runs it); and the bench's loop
(`gpmppi bench planner --vs pytorch-mppi`: the GP with fixed weights, with moving weights and `prepare`, the plain
unicycle and pytorch_mppi, interleaved in a seeded order). For measuring, not for a plan.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import numpy as np

from gpmppi.mppi import backends, cpu_backend
from gpmppi.mppi.costs import weight_vector
from gpmppi.mppi.dynamics import velocity_coefficients
from tools.profile_planner import PHASES, _cycles_per_ms, _profiled_worker

LINE = 64  # bytes in a cache line
ROW = 16  # bytes in a collapsed table row (4 float32)


class _Hook:
    """The rollout kernel's stand-in: alternates the two measures plan by plan, and keeps each plan's figures."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.calls = 0
        self.rows: dict[str, list[float]] = defaultdict(list)
        self.prev_lines: np.ndarray | None = None
        self.real = cpu_backend.rollout_kernel

    def __call__(self, model: tuple, task: tuple, sampling: tuple, cost: tuple, out: tuple) -> None:
        self.calls += 1
        if self.calls % 2:
            for name in ("cold", "warm"):
                t0 = time.perf_counter()
                self.real(model, task, sampling, cost, out)
                self.rows[f"kernel_{name}"].append((time.perf_counter() - t0) * 1e3)
            return
        samples, horizon = out.eps_out.shape[0], sampling.nominal.shape[0]
        simplex = model.table.shape[0] > 16
        record = np.zeros((samples, horizon, 5) if simplex else (0, 0, 5), dtype=np.uint64)
        for name in ("cold", "warm"):
            plan_consts = (velocity_coefficients(model.theta, model.lateral), model.table.reshape(-1),
                           np.zeros(1, dtype=np.int64))
            ticks = np.zeros(len(PHASES), dtype=np.uint64)
            _profiled_worker(model, task, sampling, weight_vector(cost), out, plan_consts,
                             cpu_backend._thread_buffers(model), ticks, record)
            for phase, v in zip(PHASES, ticks / self.rate, strict=True):
                self.rows[f"{name}_{phase}"].append(float(v))
            self.rows[f"{name}_all"].append(float(ticks.sum() / self.rate))
            if record.shape[0] > 0:
                self._count_lines(model.table, record)
                record = np.zeros((0, 0, 5), dtype=np.uint64)  # the cold run's lookups only

    def _count_lines(self, table: np.ndarray, record: np.ndarray) -> None:
        base = table.ctypes.data
        lines = (base + record.astype(np.int64) * ROW) // LINE
        per_lookup = lines.reshape(-1, 5)
        srt = np.sort(per_lookup, axis=1)
        self.rows["lines_per_lookup"].append(float(np.mean(1 + np.count_nonzero(np.diff(srt, axis=1), axis=1))))
        uniq = np.unique(lines)
        self.rows["lines_per_plan"].append(float(uniq.size))
        if self.prev_lines is not None:
            self.rows["lines_in_prev_plan"].append(float(np.intersect1d(uniq, self.prev_lines).size))
        self.prev_lines = uniq


def _bench_runners(model: object, samples: int, horizon: int) -> dict[str, object]:
    """The bench's runners (`tools.bench_planner.run_bench` with `--vs pytorch-mppi`, and the moving-weights GP)."""
    from gpmppi.mppi.planner import PlannerConfig
    from tools.bench_planner import _Ours, _Peer

    weights = np.linspace(1.0, 2.0, len(model.terrains))  # type: ignore[attr-defined]
    weights /= weights.sum()
    common = {"samples": samples, "horizon": horizon, "backend": "cpu"}
    runners: dict[str, object] = {
        "gp_fixed": _Ours(PlannerConfig(dynamics="gp", **common), model, weights),
        "gp_moving": _Ours(PlannerConfig(dynamics="gp", **common), model, weights, online_weights=True),
        "unicycle": _Ours(PlannerConfig(dynamics="unicycle", **common), model, weights),
    }
    cfg = runners["gp_fixed"].planner.config  # type: ignore[attr-defined]
    runners["peer"] = _Peer(samples, horizon, cfg.dt, cfg.noise_std, cfg.temperature)
    return runners


def run_bench_cells(plans: int, rate: float) -> dict[str, dict[str, list[float]]]:
    """The bench's loop, `plans` rounds after 5 untimed: each of our runners' plans through its own hook."""
    from tools.bench_planner import _load_model

    model, _ = _load_model()
    runners = _bench_runners(model, 1024, 40)
    hooks = {name: _Hook(rate) for name in runners if name != "peer"}
    order = np.random.default_rng(0)
    for i in range(5 + plans):
        for name in order.permutation(list(runners)):
            hook = hooks.get(name)
            backends.rollout_kernel = hook if (hook is not None and i >= 5) else cpu_backend.rollout_kernel
            try:
                runners[name].step()  # type: ignore[attr-defined]
            finally:
                backends.rollout_kernel = cpu_backend.rollout_kernel
    return {f"bench {name}": hook.rows for name, hook in hooks.items()}


def run_loop_cells(cells: list[str], models: list[str], rate: float) -> dict[str, dict[str, list[float]]]:
    """The closed loop's cells (`tools.profile_loop`), each run once untimed first."""
    from gpmppi.evaluation.runner import Job
    from tools.evaluate_jobs import load_lanes, load_scenes
    from tools.profile_loop import quick_settings, run_cell

    settings = quick_settings()
    scenarios = {**load_lanes(None), **load_scenes(None)}

    def job(label: str, model: str) -> Job:
        kind = "avoidance" if label == "avoidance" else "tracking"
        seeds = tuple(range(5)) if kind == "avoidance" else (0,)
        return Job(kind, scenarios[label], "asphalt", model, seeds, label=label)  # type: ignore[arg-type]

    for label in cells:
        for m in models:
            run_cell(job(label, m), settings)
    out = {}
    for label in cells:
        for m in models:
            hook = _Hook(rate)
            backends.rollout_kernel = hook
            try:
                run_cell(job(label, m), settings)
            finally:
                backends.rollout_kernel = cpu_backend.rollout_kernel
            out[f"loop {label} {m}"] = hook.rows
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", default="square,avoidance", help="closed-loop cells (square, avoidance, circle)")
    ap.add_argument("--models", default="gp,unicycle", help="closed-loop models")
    ap.add_argument("--bench-plans", type=int, default=60, help="plans of each bench runner (0: no bench)")
    args = ap.parse_args()
    rate = _cycles_per_ms()
    results = run_loop_cells(args.cells.split(","), args.models.split(","), rate) if args.cells else {}
    if args.bench_plans:
        results.update(run_bench_cells(args.bench_plans, rate))
    keys = ["kernel_cold", "kernel_warm", "cold_all", "warm_all"]
    keys += [f"{t}_{p}" for p in ("request_rows", "read_rows", "ensure_slabs", "advance", "add_costs", "draw")
             for t in ("cold", "warm")]
    keys += ["lines_per_plan", "lines_in_prev_plan", "lines_per_lookup"]
    print("mean over plans [ms; lines]; kernel_*: the planner's threads, the rest one thread (cycle counter)")
    for cell, rows in results.items():
        print(f"{cell} (plans {len(rows.get('kernel_cold', []))} + {len(rows.get('cold_all', []))})")
        print("  " + "  ".join(f"{k} {np.mean(rows[k]):.3f}" for k in keys if rows.get(k)))


if __name__ == "__main__":
    main()
