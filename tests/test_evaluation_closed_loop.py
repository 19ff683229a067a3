"""A short closed loop with the real planner, terrain estimator and physics plant; and the CLI end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpmppi.evaluation.runner import EvalSettings, Job, run_job, summarize
from gpmppi.scenarios import circle_lane, load_lane, paper_obstacle_scene, shipped_lane_files
from tools.cli import app

SHORT = EvalSettings(lane_distance_m=15.0, samples=512)


def _terrain() -> str:
    from cached_models import shipped_model

    return shipped_model().terrains[0]


def test_gp_beats_unicycle_on_a_short_circle() -> None:
    terrain = _terrain()
    cells = {}
    for model in ("gp", "unicycle"):
        scores, trajs = run_job(Job("tracking", circle_lane(), terrain, model, (0,), record=True), SHORT)
        assert trajs[0].status == "distance", trajs[0].message
        cells[model] = summarize(scores)
        if model == "gp":
            # the estimator ran every cycle and its weights stayed on the simplex
            w = trajs[0].weights
            assert trajs[0].weights_ok[1:].mean() > 0.9
            np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
            assert np.all(w >= -1e-9)
    assert cells["gp"]["rmse_mm"] < cells["unicycle"]["rmse_mm"], cells


def test_avoidance_run_is_deterministic_per_seed() -> None:
    terrain = _terrain()
    job = Job("avoidance", paper_obstacle_scene(), terrain, "gp", (5,), record=True)
    (a,), (ta,) = run_job(job, SHORT)
    (b,), (tb,) = run_job(job, SHORT)
    np.testing.assert_array_equal(ta.true_states, tb.true_states)
    assert a.success == b.success and a.status == b.status


def test_warm_up_plan_leaves_the_runs_as_they_were() -> None:
    """The untimed warm-up plan (a planner of its own, once per process) changes no run: a job run after it drives
    to the bit what it drives when this process has warmed that planner already."""
    from gpmppi.evaluation import runner

    settings = EvalSettings(samples=256, goal_time_limit_s=1.5)
    job = Job("avoidance", paper_obstacle_scene(), _terrain(), "gp", (3,), record=True)
    runner._WARM.clear()
    (a,), (ta,) = run_job(job, settings)
    assert len(runner._WARM) == 1
    (b,), (tb,) = run_job(job, settings)
    assert len(runner._WARM) == 1  # once per process and settings
    assert len(ta.commands) == 15
    np.testing.assert_array_equal(ta.commands, tb.commands)
    np.testing.assert_array_equal(ta.true_states, tb.true_states)
    np.testing.assert_array_equal(ta.weights, tb.weights)


def test_task_prepared_before_the_first_state_leaves_the_plans_as_they_were() -> None:
    """The goal field is built before the loop (off the steps' clock) from the first measured state, as the first plan
    would build it: the run is the same to the bit as one whose first plan builds it."""
    from gpmppi.evaluation.closed_loop import ClosedLoopConfig, run_closed_loop
    from gpmppi.evaluation.runner import cached_gp_model, make_planner, make_plant
    from gpmppi.mppi import goal_field

    settings = EvalSettings(samples=256)
    scene, model = paper_obstacle_scene(), cached_gp_model(None)
    runs = []
    for prepared in (True, False):
        goal_field._FIELDS._items.clear()  # each run builds its own field
        planner = make_planner(settings, "unicycle", _terrain(), 2)
        if not prepared:
            planner.prepare_task = None  # the loop finds no `prepare_task`: the first plan builds the field
        plant = make_plant(settings, _terrain(), 2)
        cfg = ClosedLoopConfig(time_limit_s=0.8, adapt_weights=False)
        runs.append(run_closed_loop(planner, plant, scene.task, scene.start, model.n_terrains, cfg))
        assert len(goal_field._FIELDS._items) == 1
    np.testing.assert_array_equal(runs[0].commands, runs[1].commands)
    np.testing.assert_array_equal(runs[0].true_states, runs[1].true_states)
    assert [t.tobytes() for t in runs[0].tightened] == [t.tobytes() for t in runs[1].tightened]


@pytest.mark.slow  # a 40 m open lane with GP-MPPI and its estimator: ~400 planner cycles
def test_open_lane_run_finishes_at_the_lane_end() -> None:
    lane = load_lane(next(p for p in shipped_lane_files() if p.name == "lane_chicane.yaml"))
    terrain = _terrain()
    (s,), (traj,) = run_job(Job("tracking", lane, terrain, "gp", (0,), record=True), EvalSettings(samples=256))
    assert traj.status == "finished" and s.success, traj.message
    end = lane.task.centerline[-1]
    assert np.linalg.norm(traj.positions[-1] - end) <= 0.5 + lane.task.half_width
    assert traj.positions[-1, 0] >= end[0] - 0.5  # the last straight runs along +x
    # waiting at the end used to pull the mean speed to ~0.5 m/s against the 1.5 m/s target
    assert s.mean_speed_mps > 0.8, s
    assert traj.terrains == [terrain] * len(traj.commands)
    assert s.true_weight_mean is not None and 0.0 <= s.true_weight_mean <= 1.0
    assert s.weight_switches_per_min is not None and s.weight_switches_per_min >= 0.0
    assert 0.0 < s.v_ref_rate_mean <= s.v_ref_rate_p95 and 0.0 < s.omega_ref_rate_mean <= s.omega_ref_rate_p95


@pytest.mark.slow  # the evaluation table end to end: three tasks, two models, two trials each
def test_cli_json_and_files(tmp_path: Path) -> None:
    res = CliRunner().invoke(
        app,
        ["evaluate", "table", "--quick", "--json", "-j", "1", "-m", "gp", "-m", "unicycle", "--trials", "2",
         "--distance", "5", "--samples", "256", "-o", str(tmp_path)],
    )
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout.strip().splitlines()[-1])
    terrain = _terrain()
    for task in ("circle", "square", "avoidance"):
        for model in ("gp", "unicycle"):
            cell = out["results"][task][terrain][model]
            assert set(cell) >= {"rmse_mm", "success", "trials", "time_to_goal_s"}
    assert out["results"]["avoidance"][terrain]["gp"]["trials"] == 2
    for name in ("results.md", "results.csv", "results.json", "trajectories_circle.png", "trajectories_avoidance.png",
                 "rmse_bars.png"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert "| Terrain |" in (tmp_path / "results.md").read_text()


def test_cli_reports_infeasible_scene_and_rejects_malformed_files(tmp_path: Path) -> None:
    bad = tmp_path / "scene_bad.yaml"
    bad.write_text("start: {x: 0, y: 0}\ngoal: [5, 0]\nobstacles: [{x: 5, y: 0, r: 1.0}]\n")
    res = CliRunner().invoke(app, ["evaluate", "avoidance", "--json", "-j", "1", "-n", "1", "-m", "unicycle",
                                   "--scene-file", str(bad), "-t", _terrain()])
    assert res.exit_code == 0, res.output
    cell = json.loads(res.stdout.strip().splitlines()[-1])["results"]["avoidance"][_terrain()]["unicycle"]
    assert cell["infeasible"] == 1 and cell["success"] == 0
    broken = tmp_path / "lane_broken.yaml"
    broken.write_text("centerline: [[0, 0], [1, 0]]\nhalf_width: -2\n")
    res = CliRunner().invoke(app, ["evaluate", "tracking", "--lane-file", str(broken)])
    assert res.exit_code == 2
    assert str(broken) in res.output.replace("\n", "") and "half_width" in res.output


@pytest.mark.parametrize("field", ["terrains.grass.mu_long"])
def test_cli_rejects_malformed_terrain_file(tmp_path: Path, field: str) -> None:
    f = tmp_path / "terrains.yaml"
    f.write_text("terrains:\n  grass: {mu_long: -1, mu_lat: 0.5, slip_scale_long: 0.1, slip_scale_lat: 0.1, "
                 "rolling: 0.01}\n")
    res = CliRunner().invoke(app, ["evaluate", "tracking", "--terrain-file", str(f), "-t", "grass"])
    assert res.exit_code == 2
    text = res.output.replace("\n", "")
    assert str(f) in text and field in text
