"""Write an evaluation's results: the paper-style table (Markdown, CSV, JSON) and PNG figures.

`results[task][terrain][model]` holds one cell's summary (see `gpmppi.evaluation.runner.summarize`);
`paths[task][terrain][model]` holds a recorded run for the figures: {"xy": (T, 2), "inflated": (K,) or None}.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from gpmppi.scenarios import Scenario
from gpmppi.tasks import TaskOutline
from tools.cli_checks import AtomicOutput, write_text_atomic

MODEL_LABELS = {"gp": "GP-MPPI", "edd5": "EDD5-MPPI", "unicycle": "Unicycle-MPPI"}
MODEL_COLOURS = {"gp": "tab:blue", "edd5": "tab:orange", "unicycle": "tab:green"}
LANE_TASKS = ("circle", "square")


# what the details table's less obvious columns are (docs/results.md says more)
COLUMNS_NOTE = """
Cells are the mean over a cell's trials, `±` their population spread. Rates are |Δv_ref| / dt and |Δω_ref| / dt
between consecutive commands (mean and 95th percentile per trial). True-terrain weight: the time-averaged weight
the estimate gave the terrain under the robot, after the first 3 s (`-` for a model without terrain weights or a
terrain the model was not trained on). Weight switches: changes of the largest-weight terrain per minute of run.
Open lanes end at their last point (status `finished`), so their RMSE and mean speed cover the driven part only.
"""


def _model_rank(model: str) -> int:
    return list(MODEL_LABELS).index(model) if model in MODEL_LABELS else len(MODEL_LABELS)


def _fmt(x: float, digits: int = 1) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _pm(c: dict, name: str, digits: int = 2) -> str:
    """`mean ± spread` of a cell metric and its `<name>_std`; `-` where it has no value."""
    m = c.get(name)
    if m is None or not math.isfinite(m):
        return "-"
    return f"{m:.{digits}f} ± {_fmt(c.get(f'{name}_std'), digits)}"


def _cell(results: dict, task: str, terrain: str, model: str) -> dict | None:
    return results.get(task, {}).get(terrain, {}).get(model)


def markdown_table(results: dict, models: list[str], terrains: list[str]) -> str:
    """Table 1 layout: a row per terrain; per model circle RMSE, square RMSE, avoidance success, time-to-goal."""
    head = ["Terrain"]
    for m in models:
        name = MODEL_LABELS.get(m, m)
        head += [f"{name} circle RMSE [mm]", f"{name} square RMSE [mm]", f"{name} success", f"{name} time-to-goal [s]"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for terrain in terrains:
        row = [terrain]
        for m in models:
            for lane in LANE_TASKS:
                c = _cell(results, lane, terrain, m)
                row.append(_fmt(c["rmse_mm"]) if c else "-")
            c = _cell(results, "avoidance", terrain, m)
            if c:
                row.append(f"{c['success']}/{c['trials']}")
                row.append(f"{_fmt(c['time_to_goal_s'], 2)} ± {_fmt(c['time_to_goal_std_s'], 2)}")
            else:
                row += ["-", "-"]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def write_tables(results: dict, meta: dict, out_dir: Path, models: list[str], terrains: list[str]) -> list[Path]:
    """results.md (paper layout + details), results.csv (one row per cell), results.json."""
    out_dir.mkdir(parents=True, exist_ok=True)
    md = markdown_table(results, models, terrains)
    details = ["", "| task | terrain | model | RMSE [mm] | success | lane exits | collisions | min clearance [m] "
               "| planner [ms/step] | mean speed [m/s] | v_ref rate mean [m/s²] | v_ref rate p95 [m/s²] "
               "| ω_ref rate mean [rad/s²] | ω_ref rate p95 [rad/s²] | true-terrain weight | weight switches [/min] |",
               "|" + "---|" * 16]
    rows = []
    for task, by_terrain in results.items():
        for terrain, by_model in by_terrain.items():
            for model, c in by_model.items():
                rows.append({"task": task, "terrain": terrain, "model": model,
                             **{k: v for k, v in c.items() if k != "statuses"}})
                details.append(
                    f"| {task} | {terrain} | {model} | {_fmt(c['rmse_mm'])} | {c['success']}/{c['trials']} "
                    f"| {c['lane_exits']} | {c['collisions']} | {_fmt(c['min_clearance_m'], 3)} "
                    f"| {_fmt(c['planner_ms'])} | {_fmt(c.get('mean_speed_mps'), 2)} "
                    f"| {_pm(c, 'v_ref_rate_mean')} | {_pm(c, 'v_ref_rate_p95')} "
                    f"| {_pm(c, 'omega_ref_rate_mean')} | {_pm(c, 'omega_ref_rate_p95')} "
                    f"| {_pm(c, 'true_weight_mean', 3)} | {_pm(c, 'weight_switches_per_min', 1)} |"
                )
    command = meta.get("command", "")
    text = f"# Closed-loop evaluation\n\nCommand: `{command}`\n\n{md}" + "\n".join(details) + "\n" + COLUMNS_NOTE
    paths = [out_dir / "results.md", out_dir / "results.csv", out_dir / "results.json"]
    write_text_atomic(paths[0], text)
    if rows:
        fields = list(rows[0])
        with AtomicOutput(paths[1]) as tmp, tmp.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=fields)
            w.writeheader()
            w.writerows(rows)
    write_text_atomic(paths[2], json.dumps({"results": results, "meta": meta}, indent=2, default=float))
    return paths


def _has_rmse(cell: dict) -> bool:
    """Whether a cell's runs have a lane RMSE (a goal's are NaN, `RunScore.rmse_mm`)."""
    v = cell.get("rmse_mm")
    return v is not None and bool(np.isfinite(v))


def _task_axes(ax, outline: TaskOutline, start: np.ndarray, inflated: list | None) -> None:  # noqa: ANN001
    """What the task's kind outlines: a lane's centre line, and its edges as the level set {distance to the centre
    line = half-width}; circles (with `inflated` radii where larger); a goal's tolerance circle; the start."""
    from matplotlib.patches import Circle

    from gpmppi.tasks import distance_to_polyline

    if outline.lane is not None:
        c, hw = outline.lane, outline.half_width
        line = np.vstack([c, c[:1]]) if outline.closed else c
        ax.plot(line[:, 0], line[:, 1], color="0.6", lw=0.8, ls="--", label="centre line")
        pad = hw * 1.5
        xs = np.linspace(c[:, 0].min() - pad, c[:, 0].max() + pad, 240)
        ys = np.linspace(c[:, 1].min() - pad, c[:, 1].max() + pad, 240)
        gx, gy = np.meshgrid(xs, ys)
        d = distance_to_polyline(np.stack([gx.ravel(), gy.ravel()], 1), c, outline.closed).reshape(gx.shape)
        ax.contour(gx, gy, d, levels=[hw], colors="0.2", linewidths=1.0)
    for i, (x, y, r) in enumerate(outline.circles):
        ax.add_patch(Circle((x, y), r, color="0.3", alpha=0.6))
        if inflated is not None and i < len(inflated) and inflated[i] > r:
            ax.add_patch(Circle((x, y), inflated[i], fill=False, ls="--", color="tab:red", lw=1.0))
    if outline.goal is not None:
        ax.add_patch(Circle(tuple(outline.goal), outline.tolerance, fill=False, color="tab:purple", lw=1.5))
        ax.plot(*start[:2], "k^")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def write_figures(
    paths: dict, scenarios: dict[str, Scenario], results: dict, out_dir: Path, terrain_names: list[str] | None = None
) -> list[Path]:
    """Lane trajectories per lane, an avoidance scene with the three paths, terrain weights, the planners' commands
    over time per task, the terrain estimator's confusion matrix, RMSE bars."""
    terrain_names = terrain_names or []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for task_name, by_terrain in paths.items():
        sc = scenarios.get(task_name)
        if sc is None or not by_terrain:
            continue
        terrains = list(by_terrain)
        fig, axes = plt.subplots(1, len(terrains), figsize=(5.0 * len(terrains), 5.0), squeeze=False)
        for ax, terrain in zip(axes[0], terrains, strict=True):
            _task_axes(ax, sc.task.outline(), sc.start, by_terrain[terrain].get("gp", {}).get("inflated"))
            for model, rec in sorted(by_terrain[terrain].items(), key=lambda kv: _model_rank(kv[0])):
                xy = np.asarray(rec["xy"])
                cell = _cell(results, task_name, terrain, model)
                extra = f" ({_fmt(cell['rmse_mm'])} mm)" if cell and _has_rmse(cell) else ""
                top = model == "gp"  # GP-MPPI on top: it is the closest to the centre line and would be hidden
                ax.plot(xy[:, 0], xy[:, 1], color=MODEL_COLOURS.get(model), lw=1.6 if top else 1.0,
                        zorder=3 if top else 2, label=MODEL_LABELS.get(model, model) + extra)
            ax.set_title(f"{task_name} on {terrain}")
            ax.legend(fontsize=8, loc="best")
        fig.tight_layout()
        p = out_dir / f"trajectories_{task_name}.png"
        fig.savefig(p, dpi=120)
        plt.close(fig)
        written.append(p)

    adaptive = [(task, terrain, rec["gp"]) for task, by_t in paths.items() for terrain, rec in by_t.items()
                if "gp" in rec and rec["gp"].get("weights") is not None and len(rec["gp"]["weights"])]
    if adaptive:
        fig, axes = plt.subplots(len(adaptive), 1, figsize=(7.0, 2.2 * len(adaptive)), squeeze=False, sharex=False)
        for ax, (task, terrain, rec) in zip(axes[:, 0], adaptive, strict=True):
            w = np.asarray(rec["weights"])
            for i in range(w.shape[1]):
                ax.plot(rec["times"], w[:, i], label=(terrain_names[i] if i < len(terrain_names) else f"w{i}"))
            ax.set_ylim(-0.05, 1.05)
            ax.set_ylabel("weight")
            ax.set_title(f"GP-MPPI terrain weights: {task} on {terrain}", fontsize=9)
            ax.legend(fontsize=7, loc="upper right")
        axes[-1, 0].set_xlabel("time [s]")
        fig.tight_layout()
        p = out_dir / "terrain_weights.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        written.append(p)

    written += _command_figures(paths, out_dir, plt)
    confusion = _confusion_figure(adaptive, terrain_names, out_dir, plt)
    if confusion is not None:
        written.append(confusion)

    lanes = [t for t in LANE_TASKS if t in results]
    if lanes:
        fig, axes = plt.subplots(1, len(lanes), figsize=(6.0 * len(lanes), 4.0), squeeze=False)
        for ax, lane in zip(axes[0], lanes, strict=True):
            terrains = list(results[lane])
            models = sorted({m for t in terrains for m in results[lane][t]}, key=_model_rank)
            width = 0.8 / max(len(models), 1)
            for j, m in enumerate(models):
                vals = [results[lane][t].get(m, {}).get("rmse_mm", np.nan) for t in terrains]
                ax.bar(np.arange(len(terrains)) + (j - (len(models) - 1) / 2) * width, vals, width,
                       color=MODEL_COLOURS.get(m), label=MODEL_LABELS.get(m, m))
            ax.set_xticks(np.arange(len(terrains)), terrains)
            ax.set_ylabel("RMSE to lane centre [mm]")
            ax.set_title(f"{lane} lane")
            ax.legend(fontsize=8)
        fig.tight_layout()
        p = out_dir / "rmse_bars.png"
        fig.savefig(p, dpi=120)
        plt.close(fig)
        written.append(p)
    return written


def _command_figures(paths: dict, out_dir: Path, plt) -> list[Path]:
    """Per task `commands_<task>.png`: v_ref and omega_ref over time of each model's recorded run, per terrain."""
    written = []
    for task_name, by_terrain in paths.items():
        terrains = [t for t, recs in by_terrain.items() if any(r.get("commands") is not None for r in recs.values())]
        if not terrains:
            continue
        fig, axes = plt.subplots(2, len(terrains), figsize=(5.0 * len(terrains), 5.0), squeeze=False, sharex="col")
        for j, terrain in enumerate(terrains):
            for model, rec in sorted(by_terrain[terrain].items(), key=lambda kv: _model_rank(kv[0])):
                u = rec.get("commands")
                if u is None or len(u) == 0:
                    continue
                u = np.asarray(u)
                t = np.asarray(rec["times"])[: len(u)]
                for i in range(2):
                    axes[i, j].plot(t, u[: len(t), i], color=MODEL_COLOURS.get(model), lw=1.0,
                                    label=MODEL_LABELS.get(model, model))
            axes[0, j].set_title(f"{task_name} on {terrain}")
            axes[0, j].set_ylabel("v_ref [m/s]")
            axes[1, j].set_ylabel("omega_ref [rad/s]")
            axes[1, j].set_xlabel("time [s]")
            axes[0, j].legend(fontsize=7, loc="lower right")
        fig.tight_layout()
        p = out_dir / f"commands_{task_name}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        written.append(p)
    return written


def _confusion_figure(adaptive: list, terrain_names: list[str], out_dir: Path, plt) -> Path | None:
    """`terrain_confusion.png`: per true terrain, the share of time after 3 s each terrain led GP-MPPI's weights,
    pooled over the recorded runs (`gpmppi.evaluation.metrics.top_terrain_confusion`)."""
    from gpmppi.evaluation.metrics import top_terrain_confusion

    runs = []
    for _, terrain, rec in adaptive:
        t = np.asarray(rec["times"], dtype=np.float64)  # each cycle's start: the last one ends a cycle later
        if t.size < 2:
            continue
        runs.append((terrain, np.append(t, t[-1] + (t[-1] - t[-2])), np.asarray(rec["weights"])))
    rows, matrix = top_terrain_confusion(runs, terrain_names)
    if not rows:
        return None
    fig, ax = plt.subplots(figsize=(1.6 + 1.3 * len(terrain_names), 1.2 + 1.0 * len(rows)))
    ax.imshow(matrix, vmin=0.0, vmax=1.0, cmap="Blues")
    for i in range(len(rows)):
        for j in range(len(terrain_names)):
            ax.text(j, i, f"{matrix[i, j]:.2f}", ha="center", va="center",
                    color="white" if matrix[i, j] > 0.6 else "black", fontsize=9)
    ax.set_xticks(range(len(terrain_names)), terrain_names)
    ax.set_yticks(range(len(rows)), rows)
    ax.set_xlabel("largest weight")
    ax.set_ylabel("terrain under the robot")
    ax.set_title("GP-MPPI terrain estimate, time after 3 s", fontsize=9)
    fig.tight_layout()
    p = out_dir / "terrain_confusion.png"
    fig.savefig(p, dpi=120)
    plt.close(fig)
    return p
