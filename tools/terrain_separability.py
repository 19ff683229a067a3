"""`gpmppi evaluate terrain-separability`: can the trained terrains be told apart where the robot drives?

Drives GP-MPPI closed loops on the physics plant (the evaluation's own runner), records each run's measured
transitions, then measures on them how far apart the terrains' GP predictions are against the predictive spread,
the log-likelihood ratio of the true terrain against each other over sliding windows, and the confusion of the
argmax-likelihood terrain (`gpmppi.terrain.separability`), and replays terrain estimators (the paper's convex
problem, the Bayesian filter, variants given by --estimator) on the same recorded transitions, scoring them with the
evaluation's `true_weight_mean` and `weight_switches_per_min`.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console

from tools.cli_checks import OUT_DIR, OUT_FILE, write_text_atomic
from tools.terrain_cmd import estimator_settings, written_by

SCENARIOS = ("circle", "square", "avoidance")
DEFAULT_ESTIMATORS = (
    "paper",
    "paper:history=50",
    "paper:gamma=0",
    "paper:gamma=1",
    "bayes",
    "bayes:command_change=online",
)


def _scenario(name: str):
    from gpmppi.scenarios import circle_lane, paper_obstacle_scene, square_lane

    return {"circle": circle_lane, "square": square_lane, "avoidance": paper_obstacle_scene}[name]()


def _record(scenario: str, terrain: str, seed: int, distance: float, switches: tuple, estimator: str) -> dict:
    from gpmppi.evaluation.runner import EvalSettings, Job, run_job

    sc = _scenario(scenario)
    kind = "avoidance" if scenario == "avoidance" else "tracking"
    settings = EvalSettings(lane_distance_m=distance, terrain_estimator=_estimator_fields(estimator))
    job = Job(kind, sc, terrain, "gp", (seed,), True, switches, scenario)  # type: ignore[arg-type]
    scores, trajs = run_job(job, settings)
    tr = trajs[0]
    return {"times": tr.times, "states": tr.measured_states, "commands": tr.commands, "weights": tr.weights,
            "terrains": np.asarray(tr.terrains), "rmse_mm": scores[0].rmse_mm,
            "true_weight_mean": np.nan if scores[0].true_weight_mean is None else scores[0].true_weight_mean,
            "weight_switches_per_min": scores[0].weight_switches_per_min}


def _estimator_fields(spec: str) -> tuple[tuple[str, object], ...]:
    """'bayes:switch_prob=0.01,temperature=2' -> (("method", "bayes"), ("switch_prob", 0.01), ...)."""
    method, _, rest = spec.partition(":")
    try:
        return estimator_settings([f"method={method}"] + [i for i in rest.split(",") if i])
    except ValueError as e:
        raise typer.BadParameter(f"--candidate {spec!r}: {e}") from None


def _replay_scores(model, rec: dict, spec: str) -> dict:
    from gpmppi.evaluation.metrics import true_weight_mean, weight_switches_per_min
    from gpmppi.terrain.estimator import make_estimator
    from gpmppi.terrain.separability import replay_named, top_changes
    from gpmppi.terrain.settings import EstimatorConfig

    est = make_estimator(model, EstimatorConfig(**dict(_estimator_fields(spec))))
    w, named = replay_named(est, rec["states"], rec["commands"])
    terrains = [str(t) for t in rec["terrains"]]
    return {"true_weight_mean": true_weight_mean(rec["times"], w, terrains, list(model.terrains)),
            "weight_switches_per_min": weight_switches_per_min(rec["times"], w, identified=named),
            "top_changes_after_3s": top_changes(rec["times"], w, identified=named)}


def _novelty_scores(model, rec: dict) -> dict:
    """The novelty test's statistic (gpmppi/terrain/novelty.py: the best ground's windowed mean residual in spreads)
    over the recorded steps it scores, replayed through the default filter: quantiles on the trained grounds and on
    the others, after each stretch's first whole window."""
    from gpmppi.terrain.estimator import make_estimator
    from gpmppi.terrain.settings import EstimatorConfig

    est = make_estimator(model, EstimatorConfig())
    test = getattr(est, "novelty", None)
    if test is None:
        return {}
    test.recorded = []
    x, u = np.asarray(rec["states"]), np.asarray(rec["commands"])
    terrains = [str(t) for t in rec["terrains"]]
    z: dict[bool, list[float]] = {True: [], False: []}
    run, last = 0, None
    for k in range(1, u.shape[0]):
        scored = len(test.recorded)
        est.observe(x[k - 1], u[k - 1], x[k])
        terrain = terrains[k - 1]
        run = run + 1 if terrain == last else 1
        last = terrain
        if len(test.recorded) > scored and run > test.calibration.window_steps and test.ready:
            z[terrain in model.terrains].append(test.statistic)
    out = {}
    for known, name in ((True, "trained"), (False, "new")):
        if z[known]:
            q = np.quantile(z[known], [0.1, 0.5, 0.99, 1.0])
            out[name] = {"steps": len(z[known]), "z_p10": float(q[0]), "z_p50": float(q[1]), "z_p99": float(q[2]),
                         "z_max": float(q[3])}
    return out


def _fmt(x) -> str:
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.2f}"


def separability_cmd(
    terrain: Annotated[list[str] | None, typer.Option("--terrain", "-t", help="Terrain(s) (repeat).")] = None,
    scenario: Annotated[list[str] | None, typer.Option("--scenario", help="circle, square, avoidance.")] = None,
    seed: Annotated[int, typer.Option("--seed", min=0, help="Planner and plant seed.")] = 0,
    distance: Annotated[float, typer.Option("--distance", min=1.0, max=1e5, help="Lane distance in m.")] = 40.0,
    record_dir: Annotated[Path, typer.Option(
        "--record-dir", metavar=OUT_DIR, help="Recordings (reused when present).")] = Path("terrain_runs"),
    estimator: Annotated[list[str] | None, typer.Option(
        "--candidate", help="Estimators to replay and compare: METHOD[:KEY=VALUE,...] (repeat).")] = None,
    drive_with: Annotated[str, typer.Option(
        "--drive-with", help="Estimator the recorded closed loops run with.")] = "paper",
    window: Annotated[list[int] | None, typer.Option(
        "--window", min=1, help="Window lengths in steps (repeat).")] = None,
    out: Annotated[Path | None, typer.Option(
        "--output", "-o", metavar=OUT_FILE, help="Write the JSON result here.")] = None,
    md: Annotated[Path | None, typer.Option(
        "--markdown", metavar=OUT_FILE, help="Write Markdown tables here.")] = None,
    switch: Annotated[list[str] | None, typer.Option(
        "--switch", help="Switch the plant's terrain mid-run: TIME:TERRAIN (repeat).")] = None,
) -> None:
    """Record closed loops, measure terrain separability on them and replay estimators (see the module doc)."""
    from gpmppi.evaluation.runner import cached_gp_model

    model = cached_gp_model(None)
    names = list(model.terrains)
    scenarios = scenario or list(SCENARIOS)
    for s in scenarios:
        if s not in SCENARIOS:
            raise typer.BadParameter(f"--scenario {s!r}: one of {SCENARIOS}")
    windows = tuple(window or (1, 10, 20, 50, 100))
    specs = list(estimator or DEFAULT_ESTIMATORS)
    switches = tuple((float(t), name) for t, _, name in (item.partition(":") for item in switch or []))
    t0 = time.perf_counter()
    recs = _recordings(record_dir, scenarios, terrain or names, seed, distance, switches, drive_with)
    result = _separability_result(model, recs, specs, windows)
    result["wall_time_s"] = round(time.perf_counter() - t0, 1)
    text = json.dumps(result, indent=1, default=float)
    if out is not None:
        write_text_atomic(out, text)
    if md is not None:
        write_text_atomic(md, markdown(json.loads(text), names))
    print(text)
    _print_summary(result)


def _recordings(record_dir: Path, scenarios: list[str], terrains: list[str], seed: int, distance: float,
                switches: tuple, drive_with: str) -> dict[str, dict]:
    """The recorded closed loops ("scenario/terrain" -> arrays), recorded into `record_dir` where not there yet."""
    console = Console(stderr=True)
    tag = "".join(f"_to{name}at{t:g}" for t, name in switches)
    record_dir.mkdir(parents=True, exist_ok=True)
    recs: dict[str, dict] = {}
    for s in scenarios:
        for t in terrains:
            f = record_dir / f"{s}_{t}{tag}_seed{seed}_{distance:g}m_{drive_with.replace(':', '_')}.npz"
            if not f.is_file():
                console.print(f"recording {s} on {t} ...")
                np.savez(f, **_record(s, t, seed, distance, switches, drive_with))
            recs[f"{s}/{t}"] = dict(np.load(f))
    return recs


def _separability_result(model, recs: dict[str, dict], specs: list[str], windows: tuple[int, ...]) -> dict:
    """Per run its closed loop's scores and the replays of `specs`; pooled, the separability measures."""
    from gpmppi.terrain.separability import pooled_separability, switch_response, top_changes

    names = list(model.terrains)
    result: dict = {"command": written_by(), "runs": {}}
    for key, rec in recs.items():
        terr = [str(x) for x in rec["terrains"]]
        result["runs"][key] = {
            "steps": len(terr), "closed_loop": {k: float(rec[k]) for k in (
                "rmse_mm", "true_weight_mean", "weight_switches_per_min")},
            "switch_response": switch_response(rec["times"], rec["weights"], terr, names),
            "closed_loop_top_changes_after_3s": top_changes(rec["times"], rec["weights"]),
            "replay": {spec: _replay_scores(model, rec, spec) for spec in specs},
            "novelty": _novelty_scores(model, rec),
        }
    runs = {key: (rec["states"], rec["commands"], [str(x) for x in rec["terrains"]]) for key, rec in recs.items()}
    result.update(pooled_separability(model, runs, windows))
    return result


def _print_summary(result: dict) -> None:
    console = Console(stderr=True)
    for key, run in result["runs"].items():
        row = "  ".join(f"{spec}: {_fmt(r['true_weight_mean'])}/{_fmt(r['weight_switches_per_min'])}"
                        for spec, r in run["replay"].items())
        console.print(f"{key}: closed loop {_fmt(run['closed_loop']['true_weight_mean'])}/"
                      f"{_fmt(run['closed_loop']['weight_switches_per_min'])}; replay {row}")


def markdown(result: dict, names: list[str]) -> str:
    """The result as Markdown tables: runs (closed loop and replays), calibration, pairs, confusion matrices."""
    lines = [f"`{result['command']}`", ""]
    specs = list(next(iter(result["runs"].values()))["replay"]) if result["runs"] else []
    lines += ["Cells: true-terrain weight / weight switches per minute (top-terrain changes after the first 3 s).", "",
              "| run | steps | closed loop: RMSE [mm] / true weight / switches [/min] | "
              + " | ".join(f"replay `{s}`" for s in specs) + " |",
              "|---|---|---|" + "---|" * len(specs)]
    for key, run in result["runs"].items():
        cl = run["closed_loop"]
        cells = [f"{_fmt(r['true_weight_mean'])} / {_fmt(r['weight_switches_per_min'])} "
                 f"({r.get('top_changes_after_3s', '-')})" for r in run["replay"].values()]
        lines.append(f"| {key} | {run['steps']} | {_fmt(cl['rmse_mm'])} / {_fmt(cl['true_weight_mean'])} / "
                     f"{_fmt(cl['weight_switches_per_min'])} ({run.get('closed_loop_top_changes_after_3s', '-')}) | "
                     + " | ".join(cells) + " |")
        for sw in run.get("switch_response", []):
            lines.append(f"|  switch at {sw['at_s']:.1f} s {sw['from']} -> {sw['to']}: weight > 0.5 after "
                         f"{_fmt(sw['seconds'])} s | | | " + " | " * len(specs))
    scopes = [(f"{scope}, GP variance as trained", sep) for scope, sep in result.get("separability", {}).items()]
    scopes += [(f"{scope}, calibrated (one command-change gain for all terrains removed, spread fitted)", sep)
               for scope, sep in result.get("separability_calibrated", {}).items()]
    scopes += [(f"{scope}, each terrain's shipped command-change gain in its prediction, spread fitted", sep)
               for scope, sep in result.get("separability_terrain_gains", {}).items()]
    for scope, sep in scopes:
        lines += ["", f"**{scope}**", "", "| true terrain | steps | mean z² v / ω | residual std v, ω | GP predictive "
                  "std v, ω | corr. with command change v, ω | gain on it v, ω | residual std without it v, ω |",
                  "|---|---|---|---|---|---|---|---|"]
        for t, c in sep["calibration"].items():
            extra = " | | "
            if "command_change_gain" in c:
                extra = " | ".join(f"{c[k][0]:+.3f}, {c[k][1]:+.3f}" if k != "residual_std_after_gain" else
                                   f"{c[k][0]:.3f}, {c[k][1]:.3f}"
                                   for k in ("command_change_corr", "command_change_gain", "residual_std_after_gain"))
            lines.append(f"| {t} | {c['steps']} | {c['z2_v']:.1f} / {c['z2_omega']:.1f} | "
                         f"{c['residual_std'][0]:.3f}, {c['residual_std'][1]:.3f} | "
                         f"{c['predicted_std'][0]:.3f}, {c['predicted_std'][1]:.3f} | {extra} |")
        wins = sorted({int(w) for p in sep["pairs"].values() for w in p["true_wins_fraction"]})
        lines += ["", "| true vs other | median d' v / ω | LLR per step mean ± std [nats] | "
                  + " | ".join(f"true wins, W={w}" for w in wins) + " |", "|---|---|---|" + "---|" * len(wins)]
        for pair, p in sep["pairs"].items():
            frac = p["true_wins_fraction"]
            cells = [_fmt(frac.get(str(w), frac.get(w))) for w in wins]
            name = pair.replace("|", " vs ")
            lines.append(f"| {name} | {p['dprime_v_median']:.2f} / {p['dprime_omega_median']:.2f} | "
                         f"{p['llr_per_step_mean']:+.2f} ± {p['llr_per_step_std']:.2f} | " + " | ".join(cells) + " |")
        for label, key in (("log-likelihood (GP mean and variance)", "confusion_loglik"),
                           ("squared error (the paper's fit, no variance)", "confusion_sq_error")):
            lines += ["", f"Confusion, argmax {label}; rows true, columns chosen ({', '.join(names)}):", ""]
            for w, mat in sep[key].items():
                rows = "; ".join(f"{names[i]}: {row}" for i, row in enumerate(mat))
                lines.append(f"- W={w}: {rows}")
    return "\n".join(lines) + "\n"


def register(ev: typer.Typer) -> None:
    """Add `gpmppi evaluate terrain-separability` to the evaluate group."""
    ev.command("terrain-separability")(separability_cmd)
