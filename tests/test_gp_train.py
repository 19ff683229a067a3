"""`gpmppi train`: MCAP logs and CSVs in, a model out; bad input gives a clear error and no file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpmppi.gp.model_file import GPModel
from gpmppi.gp.train import Transitions, residual_targets, select_training_data
from gpmppi.models.dynamic_unicycle import velocity_step_exact
from tools.cli import app
from tools.train_data import read_log_series

runner = CliRunner()
THETA = np.array([0.2, 0.3, 0.05, 1.0, 0.15, 1.05])
DT = 0.1


def true_residual(x: np.ndarray, terrain: int) -> np.ndarray:
    """A smooth terrain-dependent residual the GP has to learn."""
    gain = (1.0, -0.6)[terrain]
    return np.column_stack([-0.05 * gain * x[:, 0] * np.abs(x[:, 1]), 0.08 * gain * np.sin(x[:, 1]) * x[:, 2]])


def synthetic_runs(n: int, seed: int) -> dict[str, dict[str, np.ndarray]]:
    """Two terrains driven by random held commands; next velocity = nominal + true residual + noise. Commands are
    held 0.5 s, every tenth 3 s (the terrain calibration's steady responses need some held that long)."""
    rng = np.random.default_rng(seed)
    out = {}
    for m, name in enumerate(("tile", "grass")):
        held = np.where(np.arange(n // 5 + 1) % 10 == 0, 30, 5)
        cmd = np.repeat(rng.uniform([0.0, -2.0], [2.0, 2.0], (n // 5 + 1, 2)), held, axis=0)[:n]
        v, w = np.zeros(n), np.zeros(n)
        for k in range(n - 1):
            x = np.array([[cmd[k, 0], cmd[k, 1], v[k], w[k]]])
            pv, pw = velocity_step_exact(THETA, x[:, 2], x[:, 3], x[:, 0], x[:, 1], DT)
            r = true_residual(x, m)[0]
            v[k + 1] = pv[0] + r[0] + rng.normal(0, 0.003)
            w[k + 1] = pw[0] + r[1] + rng.normal(0, 0.003)
        out[name] = {"v": v, "w": w, "v_ref": cmd[:, 0], "w_ref": cmd[:, 1]}
    return out


def write_log(path: Path, runs: dict[str, dict[str, np.ndarray]], labels: bool) -> None:
    from schemas.messages import Command, Header, State, TerrainLabel
    from services.recording.mcap_writer import McapWriter

    t0 = 0
    with McapWriter(path) as w:
        for name, r in runs.items():
            for k in range(len(r["v"])):
                h = Header(stamp_ns=t0 + k * int(DT * 1e9))
                w.write("gpmppi/jackal/state", State(header=h, x=0, y=0, theta=0, v=r["v"][k], omega=r["w"][k]))
                w.write("gpmppi/jackal/cmd", Command(header=h, v_ref=r["v_ref"][k], omega_ref=r["w_ref"][k]))
                if labels:
                    w.write("gpmppi/jackal/terrain/label", TerrainLabel(header=h, terrain=name))
            t0 += (len(r["v"]) + 20) * int(DT * 1e9)  # a gap between terrains: a new segment


@pytest.fixture(scope="module")
def runs() -> dict[str, dict[str, np.ndarray]]:
    return synthetic_runs(1500, seed=1)


def test_log_reader_recovers_the_series(runs, tmp_path: Path) -> None:
    log = tmp_path / "d.mcap"
    write_log(log, runs, labels=True)
    series = read_log_series(log, DT, None, None)
    assert sorted(series) == ["grass", "tile"]
    for name, r in runs.items():
        for k in ("v", "w", "v_ref", "w_ref"):
            np.testing.assert_allclose(series[name][k], r[k], err_msg=f"{name} {k}")
        assert len(np.unique(series[name]["seg"])) == 1


@pytest.mark.slow(seconds=5)  # a model's training from a log
def test_train_from_labeled_log_learns_the_residual(runs, tmp_path: Path) -> None:
    log = tmp_path / "d.mcap"
    write_log(log, runs, labels=True)
    out = tmp_path / "m.npz"
    result = runner.invoke(app, ["train", str(log), "-o", str(out), "--points", "120", "--iters", "60",
                                 "--grid-nodes", "6"])
    assert result.exit_code == 0, result.output
    assert "RMSE nominal+GP" in result.output
    model = GPModel.load(out)
    assert model.terrains == ["grass", "tile"] and model.has_stored_grid()
    # theta is identified from the data (it absorbs part of the residual, so only the main terms are close)
    np.testing.assert_allclose(model.theta[[0, 1, 3, 5]], THETA[[0, 1, 3, 5]], rtol=0.15)
    rng = np.random.default_rng(9)
    x = rng.uniform([0.2, -1.5, 0.2, -1.5], [1.8, 1.5, 1.8, 1.5], (300, 4))
    from gpmppi.gp.exact import ExactPredictor

    mean, _ = ExactPredictor(model).predict(x)
    cols = [x[:, i].copy() for i in (2, 3, 0, 1)]
    nominal = np.column_stack(velocity_step_exact(model.theta, *cols, DT))
    for m, name in enumerate(("tile", "grass")):
        truth = np.column_stack(velocity_step_exact(THETA, *cols, DT)) + true_residual(x, m)
        t = model.task_index(name, "v")
        err_nominal = np.sqrt(np.mean((nominal - truth) ** 2))
        err_gp = np.sqrt(np.mean((nominal + mean[:, t : t + 2] - truth) ** 2))
        assert err_gp < 0.35 * err_nominal, (name, err_gp, err_nominal)


def test_unlabeled_log_needs_a_terrain_name(runs, tmp_path: Path) -> None:
    log = tmp_path / "robot.mcap"
    write_log(log, {"tile": runs["tile"]}, labels=False)
    out = tmp_path / "m.npz"
    result = runner.invoke(app, ["train", str(log), "-o", str(out)])
    assert result.exit_code == 2 and "--terrain" in result.output and not out.exists()
    result = runner.invoke(app, ["train", str(log), "-o", str(out), "--terrain", "concrete", "--points", "40",
                                 "--iters", "10", "--grid-nodes", "3"])
    assert result.exit_code == 0, result.output
    assert GPModel.load(out).terrains == ["concrete"]


def _csv(path: Path, header: str, rows: list[str]) -> Path:
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


HEADER = "cmd_lin,cmd_ang,curr_lin,curr_ang,Tile_Lin_Error,Tile_Ang_Error"


@pytest.mark.parametrize(
    ("header", "rows", "extra", "message"),
    [
        ("cmd_lin,cmd_ang,curr_lin,Tile_Lin_Error,Tile_Ang_Error", ["1,0,1,0,0"], [],
         "missing input column 'curr_ang'"),
        (HEADER, ["1,0,1,0,0.01,0", "1,0.5,nan,0,0,0"], [], ":3: column 'curr_lin' is 'nan'"),
        (HEADER, ["1,0,1,0,0.01,0"], ["--terrain", "sand"], "unknown terrain(s) ['sand']"),
        (HEADER, [], [], "no data rows"),
        ("", [], [], "no data rows"),
        ("cmd_lin,cmd_ang,curr_lin,curr_ang", ["1,0,1,0"], [], "no residual columns"),
        (HEADER, ["1,0,1,0,0.01,x"], [], "holds 'x', not a number"),
    ],
)
def test_bad_csv_input(tmp_path: Path, header: str, rows: list[str], extra: list[str], message: str,
                       jackal_free_theta: Path) -> None:
    data = _csv(tmp_path / "d.csv", header, rows)
    out = tmp_path / "m.npz"
    result = runner.invoke(app, ["train", str(data), "-o", str(out), "--theta", str(jackal_free_theta), *extra])
    assert result.exit_code == 2
    assert message in " ".join(result.output.split()), result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.csv", "theta.json"]  # no output, no temp file


@pytest.fixture
def jackal_free_theta(tmp_path: Path) -> Path:
    p = tmp_path / "theta.json"
    p.write_text('{"theta": [0.2, 0.3, 0.05, 1.0, 0.15, 1.05]}')
    return p


def test_csv_without_theta_is_refused(tmp_path: Path) -> None:
    data = _csv(tmp_path / "d.csv", HEADER, ["1,0,1,0,0.01,0"])
    result = runner.invoke(app, ["train", str(data), "-o", str(tmp_path / "m.npz")])
    assert result.exit_code == 2 and "--theta" in result.output


def test_missing_and_unreadable_logs(tmp_path: Path) -> None:
    out = tmp_path / "m.npz"
    result = runner.invoke(app, ["train", str(tmp_path / "none.mcap"), "-o", str(out)])
    assert result.exit_code == 2 and "none.mcap" in result.output and not out.exists()
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    result = runner.invoke(app, ["train", str(junk), "-o", str(out)])
    assert result.exit_code == 2 and "junk.mcap" in result.output and not out.exists()


def test_unshared_inputs_use_cluster_centres_and_local_averages() -> None:
    rng = np.random.default_rng(0)
    xa, xb = rng.uniform(0, 1, (400, 4)), rng.uniform(0, 1, (500, 4))
    sets = {"a": Transitions(xa, np.column_stack([xa[:, 0], -xa[:, 1]])),
            "b": Transitions(xb, np.column_stack([2 * xb[:, 2], xb[:, 3]]))}
    x, y = select_training_data(sets, 50, seed=0)
    assert x.shape == (50, 4) and y.shape == (4, 50)
    # local averages of a linear function stay close to its value at the centre
    np.testing.assert_allclose(y[0], x[:, 0], atol=0.15)
    np.testing.assert_allclose(y[2], 2 * x[:, 2], atol=0.3)
    shared = {"a": Transitions(xa, xa[:, :2]), "b": Transitions(xa, xa[:, 2:])}
    x2, y2 = select_training_data(shared, 50, seed=0)
    rows = [np.flatnonzero((xa == r).all(1))[0] for r in x2]  # shared inputs: actual samples
    np.testing.assert_array_equal(y2[0], xa[rows, 0])


def test_residual_targets_vanish_for_nominal_data() -> None:
    x = np.array([[1.0, 0.5, 0.8, 0.1], [0.0, -1.0, 0.3, 0.0]])
    pv, pw = velocity_step_exact(THETA, x[:, 2].copy(), x[:, 3].copy(), x[:, 0].copy(), x[:, 1].copy(), DT)
    np.testing.assert_allclose(residual_targets(THETA, x, np.column_stack([pv, pw]), DT), 0.0, atol=1e-15)


def test_labeled_log_rejects_an_unknown_terrain(runs, tmp_path: Path) -> None:
    log = tmp_path / "d.mcap"
    write_log(log, runs, labels=True)
    out = tmp_path / "m.npz"
    result = runner.invoke(app, ["train", str(log), "-o", str(out), "--terrain", "sand"])
    assert result.exit_code == 2 and "unknown terrain(s) ['sand']" in " ".join(result.output.split())
    assert not out.exists()


def test_log_reader_restarts_its_grid_after_a_gap_of_no_whole_ticks(runs, tmp_path: Path) -> None:
    """A stack recording's first state can come 1.37 s before the rest (the drive starts later): the ticks after
    the gap are read on a grid of their own, not lost for being 70 ms off the first state's."""
    from schemas.messages import Command, Header, State, TerrainLabel
    from services.recording.mcap_writer import McapWriter

    r = runs["tile"]
    log = tmp_path / "gap.mcap"
    with McapWriter(log) as w:
        for k, stamp in [(0, 0)] + [(k, 1_370_000_000 + k * int(DT * 1e9)) for k in range(1, 200)]:
            h = Header(stamp_ns=stamp)
            w.write("gpmppi/jackal/state", State(header=h, x=0, y=0, theta=0, v=r["v"][k], omega=r["w"][k]))
            w.write("gpmppi/jackal/cmd", Command(header=h, v_ref=r["v_ref"][k], omega_ref=r["w_ref"][k]))
            w.write("gpmppi/jackal/terrain/label", TerrainLabel(header=h, terrain="tile"))
    series = read_log_series(log, DT, None, None)["tile"]
    np.testing.assert_allclose(series["v"], r["v"][:200])
    assert len(np.unique(series["seg"])) == 2  # the lone first state, then one segment
