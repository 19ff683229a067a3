"""`gpmppi bench planner`: time one planner iteration (p50/p99 ms, Hz), optionally against pytorch_mppi.

The planner runs in closed loop on the circle lane (kinematic plant) so the warm start is
realistic; weights of 3 terrains are fixed (the grid table collapse then happens once), or with
`--online-weights` move a little every iteration, as when the terrain estimator re-solves each
cycle. Then, as in the planner service, the new weights are handed to `Planner.prepare` when
they arrive (it collapses ahead the table slabs the last plans read, off the state -> command
path; timed apart as `prepare`) and the state then to `plan` (`--collapse-in-plan`: no
`prepare`, the plan collapses what it reads); a planner with fixed weights runs interleaved in
the same process and the moving / fixed ratio of the plans' p50 is reported.
With `--vs pytorch-mppi` the same kinematic-unicycle problem (same S, N, dt,
noise, lambda; a simple quadratic lane-tracking cost) runs through pytorch_mppi in the same
process, interleaved with our plain (unicycle) and our chosen-model iterations, in a new seeded order each
iteration.
"""

from __future__ import annotations

import json
import time
from enum import Enum
from typing import Annotated

import numpy as np
import typer

from gpmppi.models.kinematic_unicycle import kinematic_step
from gpmppi.scenarios import circle_lane
from tools.choices import ModelName
from tools.cli_checks import fail, only_with


class GpChoice(str, Enum):
    grid = "grid"
    exact = "exact"


class BackendChoice(str, Enum):
    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"


class CollapseChoice(str, Enum):
    lazy = "lazy"
    whole = "whole"


class Peer(str, Enum):
    pytorch_mppi = "pytorch-mppi"


def _load_model():
    """The shipped model if there is one, else a synthetic one of the default grid size."""
    from gpmppi.gp.grid import DEFAULT_NODES
    from gpmppi.gp.model_file import DEFAULT_MODEL_PATH, load_default_model

    if DEFAULT_MODEL_PATH.is_file():
        return load_default_model(), "default"
    from gpmppi.mppi.synthetic import synthetic_model

    return synthetic_model(nodes=DEFAULT_NODES, n_train=300), "synthetic"


class _Ours:
    """One of our planners in closed loop on the circle lane."""

    def __init__(self, config, model, weights: np.ndarray, online_weights: bool = False, prepare: bool = True) -> None:
        from gpmppi.mppi.planner import Planner

        self.scenario = circle_lane()
        self.planner = Planner(config, model)
        self.weights = weights
        self.x = self.scenario.start.copy()
        self.online_weights = online_weights
        self.prepare = prepare
        self.prepare_ms: list[float] = []
        self.phases_ms: list[dict[str, float]] = []  # each plan's `timings_ms`
        self.rng = np.random.default_rng(0)
        if self.planner.device is not None:  # CUDA: time the uploads, the kernel and the copies back (CUDA events)
            self.planner.device.timed = True

    def step(self) -> float:
        if self.online_weights:  # a small seeded walk on the simplex, as the estimator's re-solves give
            w = np.clip(self.weights + self.rng.normal(0.0, 0.01, self.weights.shape), 0.01, 1.0)
            self.weights = w / w.sum()
            if self.prepare:  # the weights arrive before the state, as in the planner service
                t0 = time.perf_counter()
                self.planner.prepare(self.weights)
                self.prepare_ms.append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        r = self.planner.plan(self.x, self.scenario.task, self.weights)
        dt_ms = (time.perf_counter() - t0) * 1e3
        self.phases_ms.append(r.timings_ms)
        self.x = kinematic_step(self.x, r.control, 0.1)
        return dt_ms

    def phases(self, warmup: int) -> dict[str, float]:
        """The p50 of each phase of the timed plans [ms]: the plan's own split, and on CUDA the device's."""
        kept = self.phases_ms[warmup:]
        out = {name: float(np.percentile([t[name] for t in kept], 50)) for name in kept[0]} if kept else {}
        device = self.planner.device
        if device is not None:
            out.update({f"cuda_{name}": float(np.percentile(ms[warmup:], 50)) for name, ms in device.phase_ms.items()
                        if ms[warmup:]})
        return out


class _Goal:
    """One of our planners in closed loop (kinematic plant) on the paper's obstacle scene, its obstacles the circles or
    the circles rasterised to a 200 x 200 grid at 5 cm (the costmap critic); back to the start at the goal."""

    def __init__(self, config, model, weights: np.ndarray, grid: bool) -> None:
        from gpmppi.costmap import rasterise_circles
        from gpmppi.mppi.planner import Planner
        from gpmppi.scenarios import PAPER_OBSTACLES, paper_obstacle_scene
        from gpmppi.tasks import GoalTask

        self.scenario = paper_obstacle_scene()
        self.task = self.scenario.task
        if grid:
            self.costmap = rasterise_circles(PAPER_OBSTACLES, 0.05, np.array([-1.5, -2.5]), np.array([8.5, 7.5]))
            assert self.costmap.shape == (200, 200)
            self.task = GoalTask(goal=self.task.goal, tolerance=self.task.tolerance, costmap=self.costmap)
        self.planner = Planner(config, model)
        self.weights = weights
        self.x = self.scenario.start.copy()

    def step(self) -> float:
        t0 = time.perf_counter()
        r = self.planner.plan(self.x, self.task, self.weights)
        dt_ms = (time.perf_counter() - t0) * 1e3
        self.x = kinematic_step(self.x, r.control, 0.1)
        if np.hypot(*(self.x[:2] - self.task.goal)) < self.task.tolerance:
            self.x = self.scenario.start.copy()
        return dt_ms


def grid_setup_ms(backend: str, repeats: int = 5) -> dict[str, float]:
    """What a new 200 x 200 grid costs before a plan reads it (p50 ms of `repeats`): its kernel arrays (the distance
    transform, `Costmap.kernel_arrays`), its goal field (`goal_field.build_goal_field`, once per grid and goal), and
    on CUDA its upload to the device (`cuda_backend.DeviceInputs`)."""
    from gpmppi.costmap import Costmap, rasterise_circles
    from gpmppi.mppi.goal_field import build_goal_field
    from gpmppi.scenarios import PAPER_OBSTACLES

    base = rasterise_circles(PAPER_OBSTACLES, 0.05, np.array([-1.5, -2.5]), np.array([8.5, 7.5]))
    times: dict[str, list[float]] = {"grid_arrays_ms": [], "goal_field_ms": [], "grid_upload_ms": []}
    for _ in range(repeats):
        grid = Costmap(base.values.copy(), base.resolution, base.origin)  # a new grid: nothing cached
        t0 = time.perf_counter()
        arrays, frame = grid.kernel_arrays()
        times["grid_arrays_ms"].append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        build_goal_field(np.array([7.0, 5.0]), np.zeros((0, 3)), np.zeros((1, 2)), margin=8.0, costmap=grid)
        times["goal_field_ms"].append((time.perf_counter() - t0) * 1e3)
        if backend == "cuda":
            from numba import cuda

            from gpmppi.mppi.cuda_backend import DeviceInputs

            device = DeviceInputs()
            t0 = time.perf_counter()
            device._array("task", "grid", arrays)
            cuda.synchronize()
            times["grid_upload_ms"].append((time.perf_counter() - t0) * 1e3)
    return {k: float(np.percentile(v, 50)) for k, v in times.items() if v}


class _Peer:
    """pytorch_mppi on the kinematic unicycle with a quadratic lane-tracking cost."""

    def __init__(self, samples: int, horizon: int, dt: float, noise: tuple[float, float], lam: float) -> None:
        import torch
        from pytorch_mppi import MPPI

        self.torch = torch
        sc = circle_lane()
        radius = float(np.hypot(*sc.task.centerline[0]))
        speed = sc.task.speed_target

        def dynamics(state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
            v = action[:, 0]
            w = action[:, 1]
            th = state[:, 2]
            return torch.stack([state[:, 0] + v * torch.cos(th) * dt, state[:, 1] + v * torch.sin(th) * dt,
                                th + w * dt], dim=1)

        def running_cost(state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
            r = torch.sqrt(state[:, 0] ** 2 + state[:, 1] ** 2)
            return (r - radius) ** 2 + (action[:, 0] - speed) ** 2

        dtype = torch.float32
        self.mppi = MPPI(
            dynamics, running_cost, 3, torch.diag(torch.tensor([noise[0] ** 2, noise[1] ** 2], dtype=dtype)),
            num_samples=samples, horizon=horizon, lambda_=lam, device="cpu",
            u_min=torch.tensor([0.0, -np.pi], dtype=dtype), u_max=torch.tensor([2.0, np.pi], dtype=dtype),
        )
        self.x = torch.tensor(sc.start[:3], dtype=dtype)

    def step(self) -> float:
        t0 = time.perf_counter()
        u = self.mppi.command(self.x)
        dt_ms = (time.perf_counter() - t0) * 1e3
        x = self.x.numpy().astype(np.float64)
        nxt = kinematic_step(np.array([x[0], x[1], x[2], 0.0, 0.0]), u.numpy().astype(np.float64), 0.1)
        self.x = self.torch.tensor(nxt[:3], dtype=self.x.dtype)
        return dt_ms


def _stats(ts: list[float]) -> dict[str, float]:
    a = np.asarray(ts)
    p50 = float(np.percentile(a, 50))
    return {"p50_ms": p50, "p99_ms": float(np.percentile(a, 99)), "hz": 1e3 / p50 if p50 > 0 else float("inf")}


def run_bench(samples: int, horizon: int, model_choice: str, gp: str, backend: str, vs: str | None, iters: int,
              warmup: int = 5, online_weights: bool = False, prepare: bool = True,
              table_collapse: str = "lazy", costmap: bool = False) -> dict:
    from gpmppi.mppi.planner import PlannerConfig

    model, source = _load_model()
    m = len(model.terrains)
    weights = np.linspace(1.0, 2.0, m)
    weights /= weights.sum()
    common = {"samples": samples, "horizon": horizon, "backend": backend, "gp_mode": gp,
              "table_collapse": table_collapse}
    runners: dict[str, object] = {
        "main": _Ours(PlannerConfig(dynamics=model_choice, **common), model, weights, online_weights, prepare)
    }
    if online_weights:
        runners["fixed"] = _Ours(PlannerConfig(dynamics=model_choice, **common), model, weights)
    cfg = runners["main"].planner.config  # type: ignore[attr-defined]
    if costmap:
        runners["circles"] = _Goal(PlannerConfig(dynamics=model_choice, **common), model, weights, grid=False)
        runners["grid"] = _Goal(PlannerConfig(dynamics=model_choice, **common), model, weights, grid=True)
    if vs is not None:
        runners["plain"] = _Ours(PlannerConfig(dynamics="unicycle", **common), model, weights)
        runners["peer"] = _Peer(samples, horizon, cfg.dt, cfg.noise_std, cfg.temperature)
    times: dict[str, list[float]] = {k: [] for k in runners}
    # interleaved, so that machine load hits all alike, in a new (seeded) order each iteration: in one fixed order
    # each runner always ran right after the same one, in the caches that one left (ours after pytorch_mppi, whose
    # tensors had evicted our GP table: docs/benchmarks.md)
    names = list(runners)
    order = np.random.default_rng(0)
    for i in range(warmup + iters):
        for name in order.permutation(names):
            t = runners[name].step()  # type: ignore[attr-defined]
            if i >= warmup:
                times[name].append(t)
    out = {"samples": samples, "horizon": horizon, "model": model_choice, "gp": gp, "table_collapse": table_collapse,
           "backend": runners["main"].planner.backend, "iters": iters, "terrains": m,  # type: ignore[attr-defined]
           "model_source": source, **_stats(times["main"]),
           "phases_p50_ms": runners["main"].phases(warmup)}  # type: ignore[attr-defined]
    if online_weights:
        fixed = _stats(times["fixed"])
        prep_ms = runners["main"].prepare_ms[warmup:]  # type: ignore[attr-defined]
        prep = _stats(prep_ms) if prep_ms else {"p50_ms": 0.0, "p99_ms": 0.0}
        out.update({
            "online_weights": True, "prepare": prepare, "fixed_p50_ms": fixed["p50_ms"],
            "fixed_p99_ms": fixed["p99_ms"], "ratio_moving_vs_fixed": out["p50_ms"] / fixed["p50_ms"],
            "prepare_p50_ms": prep["p50_ms"], "prepare_p99_ms": prep["p99_ms"],
            "ratio_cycle_vs_fixed": (out["p50_ms"] + prep["p50_ms"]) / fixed["p50_ms"],
        })
    if costmap:
        circles, grid = _stats(times["circles"]), _stats(times["grid"])
        out.update({
            "costmap": True, "circles_p50_ms": circles["p50_ms"], "circles_p99_ms": circles["p99_ms"],
            "grid_p50_ms": grid["p50_ms"], "grid_p99_ms": grid["p99_ms"],
            "ratio_grid_vs_circles": grid["p50_ms"] / circles["p50_ms"],
            **grid_setup_ms(out["backend"]),
        })
    if vs is not None:
        plain, peer = _stats(times["plain"]), _stats(times["peer"])
        out.update({
            "plain_p50_ms": plain["p50_ms"], "plain_p99_ms": plain["p99_ms"],
            "peer": vs, "peer_p50_ms": peer["p50_ms"], "peer_p99_ms": peer["p99_ms"],
            "ratio_gp_vs_peer": out["p50_ms"] / peer["p50_ms"],
            "ratio_plain_vs_peer": plain["p50_ms"] / peer["p50_ms"],
            "ratio_gp_vs_plain": out["p50_ms"] / plain["p50_ms"],
        })
    return out


def register(app: typer.Typer) -> None:
    """Add `bench planner`."""

    @app.command("planner")
    def planner_cmd(
        samples: Annotated[int, typer.Option("--samples", min=1, max=1 << 20, help="Samples S")] = 1024,
        horizon: Annotated[int, typer.Option("--horizon", min=1, max=1000, help="Horizon N")] = 40,
        model: Annotated[ModelName, typer.Option("--model", "-m", help="Rollout model")] = ModelName.gp,
        gp: Annotated[GpChoice, typer.Option("--gp", help="GP evaluation")] = GpChoice.grid,
        backend: Annotated[BackendChoice, typer.Option("--backend", help="Kernel backend")] = BackendChoice.auto,
        vs: Annotated[Peer | None, typer.Option("--vs", help="Also time a peer MPPI on the same problem")] = None,
        as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object")] = False,
        iters: Annotated[int, typer.Option(
            "--iters", min=1, max=1_000_000, help="Timed iterations (after 5 warm-up)")] = 50,
        online_weights: Annotated[
            bool, typer.Option("--online-weights", help="Move the terrain weights every iteration (table collapse)")
        ] = False,
        table_collapse: Annotated[
            CollapseChoice, typer.Option("--table-collapse", help="GP table: collapsed lazily (on CUDA: on the device) "
                                         "or whole (on CUDA: on the host, then uploaded)")
        ] = CollapseChoice.lazy,
        collapse_in_plan: Annotated[
            bool, typer.Option("--collapse-in-plan",
                               help="With --online-weights: no Planner.prepare, the plan collapses what it reads")
        ] = False,
        costmap: Annotated[
            bool, typer.Option("--costmap", help="Also time the paper's obstacle scene with its circles and with them "
                               "rasterised to a 200 x 200 grid (the costmap critic), interleaved, and a new grid's "
                               "setup (distance transform, goal field, upload)")
        ] = False,
    ) -> None:
        """Time planner iterations: p50/p99 ms and Hz (the machine's load adds noise: re-run when quiet)."""
        only_with(online_weights, "--online-weights", {"--collapse-in-plan": collapse_in_plan})
        only_with(model is ModelName.gp, "--model gp", {"--gp": gp is not GpChoice.grid,
                                                        "--table-collapse": table_collapse is not CollapseChoice.lazy})
        try:
            res = run_bench(samples, horizon, model.value, gp.value, backend.value, vs.value if vs else None, iters,
                            online_weights=online_weights, prepare=not collapse_in_plan,
                            table_collapse=table_collapse.value, costmap=costmap)
        except ValueError as e:  # e.g. --backend cuda on a machine without a GPU
            fail(str(e))
        if as_json:
            typer.echo(json.dumps(res))
            return
        typer.echo(
            f"planner {res['model']}/{res['gp']} on {res['backend']}, S={samples} N={horizon}, "
            f"{res['terrains']} terrains ({res['model_source']} model), {iters} iterations"
        )
        typer.echo(f"  ours:  p50 {res['p50_ms']:.2f} ms  p99 {res['p99_ms']:.2f} ms  {res['hz']:.0f} Hz")
        typer.echo("  phases (p50 ms): " + ", ".join(f"{k} {v:.3f}" for k, v in res["phases_p50_ms"].items()))
        if online_weights:
            typer.echo(f"  fixed weights: p50 {res['fixed_p50_ms']:.2f} ms  p99 {res['fixed_p99_ms']:.2f} ms")
            where = "prepare (weights arrive)" if res["prepare"] else "no prepare (--collapse-in-plan)"
            typer.echo(
                f"  {where}: p50 {res['prepare_p50_ms']:.2f} ms  p99 {res['prepare_p99_ms']:.2f} ms; moving / fixed: "
                f"plan {res['ratio_moving_vs_fixed']:.3f}x, prepare + plan {res['ratio_cycle_vs_fixed']:.3f}x"
            )
        if costmap:
            typer.echo(f"  paper scene, circles: p50 {res['circles_p50_ms']:.2f} ms  "
                       f"p99 {res['circles_p99_ms']:.2f} ms; "
                       f"200 x 200 grid: p50 {res['grid_p50_ms']:.2f} ms  p99 {res['grid_p99_ms']:.2f} ms; "
                       f"grid / circles {res['ratio_grid_vs_circles']:.3f}x")
            typer.echo("  a new grid (p50 ms): " + ", ".join(
                f"{k[:-3]} {res[k]:.2f}" for k in ("grid_arrays_ms", "goal_field_ms", "grid_upload_ms") if k in res))
        if vs is not None:
            typer.echo(f"  plain: p50 {res['plain_p50_ms']:.2f} ms  p99 {res['plain_p99_ms']:.2f} ms")
            typer.echo(f"  {res['peer']}: p50 {res['peer_p50_ms']:.2f} ms  p99 {res['peer_p99_ms']:.2f} ms")
            typer.echo(
                f"  ratios: ours/peer {res['ratio_gp_vs_peer']:.2f}, plain/peer {res['ratio_plain_vs_peer']:.2f}, "
                f"ours/plain {res['ratio_gp_vs_plain']:.2f}"
            )
