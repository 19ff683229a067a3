"""The fit's coverage report: cells of the planner's range counted per ground, held commands found in a log's time
series, thin cells named as what to drive, and a ground with too little data refused before anything is fitted."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from gpmppi.gp.coverage import MIN_PER_CELL, V_EDGES, W_EDGES, cells, ground_coverage, held_commands
from tools.cli import app


def test_cells_count_each_sample_once_and_clip_to_the_range() -> None:
    v = np.array([0.1, 0.6, 1.9, 2.5, -0.2])  # 2.5 and -0.2 fall in the edge cells
    w = np.array([0.1, -3.0, 3.1, 0.0, 10.0])
    c = cells(v, w)
    assert c.shape == (len(V_EDGES) - 1, len(W_EDGES) - 1) and c.sum() == len(v)
    assert c[0, 3] == 1 and c[1, 0] == 1 and c[3, 5] == 1 and c[3, 3] == 1 and c[0, 5] == 1


def test_held_commands_are_runs_of_one_command_lasting_a_second() -> None:
    dt = 0.1
    v = np.r_[np.full(15, 1.0), np.full(5, 0.5), np.full(10, 0.8), np.linspace(0, 1, 20)]
    w = np.zeros_like(v)
    seg = np.zeros(len(v), dtype=int)
    assert held_commands(v, w, seg, dt) == 2  # 1.5 s and 1.0 s; 0.5 s and the ramp are not held
    seg[20:] = 1
    seg[25:30] = 2  # a segment change splits the 1.0 s run
    assert held_commands(v, w, seg, dt) == 1


def test_a_narrow_drive_is_thin_and_a_wide_one_covers_the_range() -> None:
    rng = np.random.default_rng(0)
    narrow = np.column_stack([rng.uniform(0.6, 0.9, 500), rng.uniform(0.1, 0.5, 500), rng.uniform(0.6, 0.9, 500),
                              rng.uniform(0.1, 0.5, 500)])
    c = ground_coverage("sand", narrow, held=0)
    assert c.command_covered == 1 / 24 and c.problem() is not None
    assert "v_ref 0.5-1.0 m/s with omega_ref +0.0..+1.0" not in c.problem()  # the one covered cell is not asked for
    assert "v_ref 1.5-2.0 m/s with omega_ref +2.1..+3.1 rad/s" in c.thin()
    wide = np.column_stack([rng.uniform(0, 2, 5000), rng.uniform(-np.pi, np.pi, 5000), rng.uniform(0, 2, 5000),
                            rng.uniform(-np.pi, np.pi, 5000)])
    c = ground_coverage("grass", wide, held=7)
    assert c.command_covered == 1.0 and c.state_covered == 1.0 and c.thin() == [] and c.problem() is None
    assert (c.command_cells >= MIN_PER_CELL).all()
    few = ground_coverage("ice", wide[:50])
    assert "50 one-step samples" in few.problem()
    still = ground_coverage("grass", wide, held=0)  # a log whose commands never stay put: no calibration
    assert "no command held 1 s or longer" in still.problem() and "hold commands" in still.problem()
    assert ground_coverage("grass", wide, held=None).problem() is None  # a CSV has no time series to hold


def _csv(path: Path, x: np.ndarray, terrain: str) -> Path:
    rows = [f"{a},{b},{c},{d},{0.01 * a},{0.0}" for a, b, c, d in x]
    path.write_text(f"cmd_lin,cmd_ang,curr_lin,curr_ang,{terrain}_Lin_Error,{terrain}_Ang_Error\n" + "\n".join(rows))
    return path


def test_train_refuses_a_ground_with_too_little_excitation_naming_what_to_drive(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    x = np.column_stack([rng.uniform(0.6, 0.9, 300), rng.uniform(0.1, 0.5, 300), rng.uniform(0.6, 0.9, 300),
                         rng.uniform(0.1, 0.5, 300)])
    theta = tmp_path / "theta.json"
    theta.write_text('{"theta": [0.2155, 0.3266, 0.0514, 1.067, 0.166, 1.079]}')
    out = tmp_path / "m.npz"
    result = CliRunner().invoke(app, ["train", str(_csv(tmp_path / "d.csv", x, "Sand")), "--theta", str(theta),
                                      "-o", str(out)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert "ground 'sand'" in lines[0] and "cover 4%" in lines[0] and "drive v_ref" in lines[0]
    assert not out.exists()
