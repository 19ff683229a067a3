"""Table and figure writers on hand-made results."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from gpmppi.evaluation.runner import RunScore, summarize
from gpmppi.scenarios import circle_lane, paper_obstacle_scene
from tools.report import markdown_table, write_figures, write_tables


def _cell(rmse: float, success: int, trials: int, ttg: float) -> dict:
    scores = [RunScore(seed=i, status="goal" if i < success else "collision", rmse_mm=rmse, success=i < success,
                       time_to_goal_s=ttg + 0.1 * i if i < success else float("nan")) for i in range(trials)]
    return summarize(scores)


def _results() -> dict:
    res: dict = {}
    for task in ("circle", "square", "avoidance"):
        for terrain in ("tile", "grass"):
            for k, model in enumerate(("gp", "edd5", "unicycle")):
                res.setdefault(task, {}).setdefault(terrain, {})[model] = _cell(20.0 + 10 * k, 4 - k, 4, 6.0)
    return res


def test_summary_of_hand_made_scores() -> None:
    c = _cell(25.0, 3, 4, 6.0)
    assert c["success"] == 3 and c["trials"] == 4 and c["collisions"] == 1
    assert np.isclose(c["rmse_mm"], 25.0)
    assert np.isclose(c["time_to_goal_s"], 6.1) and np.isclose(c["time_to_goal_std_s"], np.std([6.0, 6.1, 6.2]))


def test_markdown_has_paper_layout() -> None:
    md = markdown_table(_results(), ["gp", "edd5", "unicycle"], ["tile", "grass"])
    lines = md.strip().splitlines()
    assert len(lines) == 4  # header, rule, one row per terrain
    header = [h.strip() for h in lines[0].strip("|").split("|")]
    assert header[0] == "Terrain" and len(header) == 1 + 3 * 4
    assert header[1:5] == ["GP-MPPI circle RMSE [mm]", "GP-MPPI square RMSE [mm]", "GP-MPPI success",
                           "GP-MPPI time-to-goal [s]"]
    tile = [c.strip() for c in lines[2].strip("|").split("|")]
    assert tile[:5] == ["tile", "20.0", "20.0", "4/4", "6.15 ± 0.11"]
    assert tile[9:11] == ["40.0", "40.0"] and tile[11] == "2/4"


def test_write_tables_and_figures(tmp_path: Path) -> None:
    res = _results()
    paths = write_tables(res, {"command": "gpmppi evaluate table"}, tmp_path, ["gp", "edd5", "unicycle"],
                         ["tile", "grass"])
    assert all(p.stat().st_size > 0 for p in paths)
    rows = list(csv.DictReader((tmp_path / "results.csv").open()))
    assert len(rows) == 3 * 2 * 3 and {r["model"] for r in rows} == {"gp", "edd5", "unicycle"}
    assert json.loads((tmp_path / "results.json").read_text())["results"]["avoidance"]["tile"]["gp"]["success"] == 4
    t = np.linspace(0, 2 * np.pi, 50)
    ring = {"xy": np.stack([8.3 * np.cos(t), 8.3 * np.sin(t)], 1), "inflated": None,
            "times": t, "weights": np.tile([0.2, 0.3, 0.5], (50, 1)), "weights_ok": np.ones(50, bool)}
    line = {"xy": np.stack([t, t], 1), "inflated": np.array([0.8, 1.0, 0.8, 0.9, 0.9]), "times": t,
            "weights": np.tile([0.2, 0.3, 0.5], (50, 1)), "weights_ok": np.ones(50, bool)}
    figs = write_figures({"circle": {"tile": {"gp": ring, "unicycle": ring}}, "avoidance": {"tile": {"gp": line}}},
                         {"circle": circle_lane(), "avoidance": paper_obstacle_scene()}, res, tmp_path,
                         ["asphalt", "grass", "tile"])
    names = {p.name for p in figs}
    assert names == {"trajectories_circle.png", "trajectories_avoidance.png", "terrain_weights.png", "rmse_bars.png"}
    assert all((tmp_path / n).read_bytes()[:4] == b"\x89PNG" for n in names)
