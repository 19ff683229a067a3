"""Table and figure writers on hand-made results."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from gpmppi.evaluation.closed_loop import ClosedLoopConfig, Trajectory
from gpmppi.evaluation.runner import RunScore, score, summarize
from gpmppi.scenarios import circle_lane, paper_obstacle_scene
from gpmppi.tasks import LaneTask
from tools.report import markdown_table, write_figures, write_tables

NAMES = ["asphalt", "grass", "tile"]


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
            "times": t, "weights": np.tile([0.2, 0.3, 0.5], (50, 1)), "weights_ok": np.ones(50, bool),
            "commands": np.stack([np.full(50, 1.2), np.sin(t)], 1)}
    line = {"xy": np.stack([t, t], 1), "inflated": np.array([0.8, 1.0, 0.8, 0.9, 0.9]), "times": t,
            "weights": np.tile([0.2, 0.3, 0.5], (50, 1)), "weights_ok": np.ones(50, bool)}
    figs = write_figures({"circle": {"tile": {"gp": ring, "unicycle": ring}}, "avoidance": {"tile": {"gp": line}}},
                         {"circle": circle_lane(), "avoidance": paper_obstacle_scene()}, res, tmp_path,
                         ["asphalt", "grass", "tile"])
    names = {p.name for p in figs}
    assert names == {"trajectories_circle.png", "trajectories_avoidance.png", "terrain_weights.png", "rmse_bars.png",
                     "commands_circle.png", "terrain_confusion.png"}
    assert all((tmp_path / n).read_bytes()[:4] == b"\x89PNG" for n in names)


def _ramp_run(terrain: str) -> Trajectory:
    """6 s on a straight lane: v_ref ramps at 2 m/s^2, omega_ref steps by 0.05 rad/s each cycle (0.5 rad/s^2); the
    weights are uniform for 3 s (top: asphalt), then put 0.8 on grass."""
    T = 60
    k = np.arange(T)
    times = np.arange(T + 1) * 0.1
    x = np.concatenate([[0.0], np.cumsum(0.1 * 0.2 * k)])
    states = np.zeros((T + 1, 5))
    states[:, 0] = x
    w = np.where(k[:, None] < 30, 1 / 3, np.array([0.1, 0.8, 0.1])[None, :])
    return Trajectory(times=times, true_states=states, measured_states=states.copy(),
                      commands=np.stack([0.2 * k, 0.05 * k], 1), weights=w, weights_ok=np.ones(T, bool),
                      planner_ms=np.ones(T), tightened=[], terrains=[terrain] * T, status="distance")


def test_score_has_the_rates_of_the_commands_the_base_received() -> None:
    """The planner steps v_ref by 0.2 m/s each 0.1 s (2 m/s^2); egress halves each step over two 20 Hz outputs, the
    second marked `limit`: the base's v changes 0.1 m/s per 0.05 s (2 m/s^2 too, but half as big a step); omega is
    held at 0.5 rad/s then jumps to -0.5 once (20 rad/s^2 over one 0.05 s output)."""
    lane = LaneTask(np.array([[0.0, 0.0], [100.0, 0.0]]), half_width=1.0, closed=True)
    run = _ramp_run("grass")
    bt = np.arange(120) * 0.05
    bv = 0.1 * np.arange(120)
    bw = np.where(np.arange(120) < 60, 0.5, -0.5)
    run.base_times, run.base_commands = bt, np.stack([bv, bw], 1)
    run.base_reasons = ["planner" if i % 2 else "limit" for i in range(120)]
    s = score(run, lane, 0, ClosedLoopConfig(adapt_weights=True), NAMES)
    assert s.base_v_rate_mean == pytest.approx(2.0) and s.base_v_rate_p95 == pytest.approx(2.0)
    assert s.base_omega_rate_mean == pytest.approx(20.0 / 119)
    assert s.base_omega_rate_p95 == pytest.approx(0.0)  # one jump in 119 changes
    assert s.base_limited_fraction == pytest.approx(0.5)
    assert s.v_ref_rate_mean == pytest.approx(2.0)  # the planner's own, unchanged
    bare = score(_ramp_run("grass"), lane, 0, ClosedLoopConfig(adapt_weights=True), NAMES)
    assert np.isnan(bare.base_v_rate_mean) and np.isnan(bare.base_limited_fraction)  # no base commands recorded
    cell = summarize([s, s])
    assert cell["base_v_rate_mean"] == pytest.approx(2.0) and cell["base_v_rate_mean_std"] == pytest.approx(0.0)


def test_score_of_a_hand_made_run_has_rates_and_weight_scores() -> None:
    lane = LaneTask(np.array([[0.0, 0.0], [100.0, 0.0]]), half_width=1.0, closed=True)
    adapting = ClosedLoopConfig(adapt_weights=True)
    s = score(_ramp_run("grass"), lane, 0, adapting, NAMES)
    assert s.v_ref_rate_mean == pytest.approx(2.0) and s.v_ref_rate_p95 == pytest.approx(2.0)
    assert s.omega_ref_rate_mean == pytest.approx(0.5) and s.omega_ref_rate_p95 == pytest.approx(0.5)
    assert s.true_weight_mean == pytest.approx(0.8)  # after 3 s: all 0.8 on grass
    # one change, at 3.0 s (counted: from 3 s on), in the 0.05 min after the first 3 s
    assert s.weight_switches_per_min == pytest.approx(20.0)
    sand = score(_ramp_run("sand"), lane, 0, adapting, NAMES)
    assert sand.true_weight_mean is None and sand.weight_switches_per_min == pytest.approx(20.0)
    fixed = score(_ramp_run("grass"), lane, 0, ClosedLoopConfig(adapt_weights=False), NAMES)
    assert fixed.true_weight_mean is None and fixed.weight_switches_per_min is None
    assert fixed.v_ref_rate_mean == pytest.approx(2.0)


def _scored(true_w: float | None, switches: float | None, v_rate: float) -> RunScore:
    return RunScore(seed=0, status="distance", rmse_mm=30.0, success=True, v_ref_rate_mean=v_rate,
                    v_ref_rate_p95=2 * v_rate, omega_ref_rate_mean=0.5, omega_ref_rate_p95=1.0,
                    true_weight_mean=true_w, weight_switches_per_min=switches)


def test_summary_of_the_new_metrics_is_mean_and_spread_over_trials() -> None:
    c = summarize([_scored(0.7, 2.0, 1.0), _scored(0.8, 4.0, 3.0), _scored(None, 6.0, float("nan"))])
    assert c["v_ref_rate_mean"] == pytest.approx(2.0) and c["v_ref_rate_mean_std"] == pytest.approx(1.0)
    assert c["v_ref_rate_p95"] == pytest.approx(4.0) and c["omega_ref_rate_p95"] == pytest.approx(1.0)
    assert c["true_weight_mean"] == pytest.approx(0.75) and c["true_weight_mean_std"] == pytest.approx(0.05)
    assert c["weight_switches_per_min"] == pytest.approx(4.0)
    assert c["weight_switches_per_min_std"] == pytest.approx(np.std([2.0, 4.0, 6.0]))
    none = summarize([_scored(None, None, 1.0)])
    assert none["true_weight_mean"] is None and none["weight_switches_per_min_std"] is None


def test_tables_show_the_new_columns(tmp_path: Path) -> None:
    res = {"chicane": {"grass": {"gp": summarize([_scored(0.7, 2.0, 1.0), _scored(0.8, 4.0, 3.0)]),
                                 "unicycle": summarize([_scored(None, None, 5.0)])}}}
    write_tables(res, {"command": "gpmppi evaluate tracking"}, tmp_path, ["gp", "unicycle"], ["grass"])
    md = (tmp_path / "results.md").read_text()
    for col in ("mean speed [m/s]", "v_ref rate mean [m/s²]", "v_ref rate p95 [m/s²]", "ω_ref rate mean [rad/s²]",
                "ω_ref rate p95 [rad/s²]", "true-terrain weight", "weight switches [/min]"):
        assert f"| {col} |" in md, col
    gp_row = next(line for line in md.splitlines() if line.startswith("| chicane | grass | gp |"))
    cells = [c.strip() for c in gp_row.strip("|").split("|")]
    assert cells[-6:] == ["2.00 ± 1.00", "4.00 ± 2.00", "0.50 ± 0.00", "1.00 ± 0.00", "0.750 ± 0.050", "3.0 ± 1.0"]
    uni_row = next(line for line in md.splitlines() if line.startswith("| chicane | grass | unicycle |"))
    assert [c.strip() for c in uni_row.strip("|").split("|")][-2:] == ["-", "-"]
    rows = {r["model"]: r for r in csv.DictReader((tmp_path / "results.csv").open())}
    assert float(rows["gp"]["true_weight_mean"]) == pytest.approx(0.75)
    assert float(rows["gp"]["v_ref_rate_p95"]) == pytest.approx(4.0)
    assert rows["unicycle"]["true_weight_mean"] == "" and rows["unicycle"]["weight_switches_per_min"] == ""
    cell = json.loads((tmp_path / "results.json").read_text())["results"]["chicane"]["grass"]
    assert cell["gp"]["weight_switches_per_min"] == pytest.approx(3.0) and cell["unicycle"]["true_weight_mean"] is None
    assert cell["unicycle"]["omega_ref_rate_mean"] == pytest.approx(0.5)
