"""`gpmppi train LOG --calibration-log CAL`: a log that feeds the terrain estimator's calibration only (steady map,
command-change gains, rate), never the GP's or the nominal model's training data; and each bad calibration log
refused in one line, writing nothing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_robot_profile import FAST, GROUNDS, _one_line_refusal, _relabelled
from typer.testing import CliRunner

from gpmppi.gp.model_file import GPModel
from tools.cli import app

runner = CliRunner()


@pytest.fixture(scope="module")
def logs(grounds_log: Path, tmp_path_factory) -> tuple[Path, Path]:
    """(training log: the plain drive of both grounds, made once a run and shared with tests/test_robot_profile.py
    (tests/conftest.py); calibration log: another drive of one ground, half of its segments lane holds)."""
    cal = tmp_path_factory.mktemp("calibration_log") / "cal.mcap"
    result = runner.invoke(app, ["dataset", "-o", str(cal), "--distance", "300", "--seed", "1", "-t", GROUNDS[0],
                                 "--lane-holds", "0.5"])
    assert result.exit_code == 0, result.output
    return grounds_log, cal


def _train(args: list[str], out: Path) -> GPModel:
    result = runner.invoke(app, ["train", *args, "-o", str(out), *FAST])
    assert result.exit_code == 0, result.output
    return GPModel.load(out)


@pytest.mark.slow(seconds=10)  # a model's training (and the plain one, once a run: tests/conftest.py)
def test_a_calibration_log_changes_the_calibration_and_leaves_the_gp_bit_for_bit(
    logs: tuple[Path, Path], grounds_profile: Path, tmp_path: Path
) -> None:
    train, cal = logs
    plain = GPModel.load(grounds_profile)  # `gpmppi train TRAIN -o OUT` + FAST, as `_train` runs it
    both = _train([str(train), "--calibration-log", str(cal)], tmp_path / "both.npz")
    # the GP, the nominal model, EDD5 and lateral slip: the same bits (the calibration log is not training data)
    for name in ("train_x", "lengthscale", "outputscale", "noise", "chol", "alpha", "theta", "domain_lo", "domain_hi"):
        assert np.array_equal(getattr(plain, name), getattr(both, name)), name
    for t in GROUNDS:
        assert np.array_equal(plain.edd5[t], both.edd5[t]) and np.array_equal(plain.lateral_slip[t],
                                                                               both.lateral_slip[t]), t
    assert plain.fit_report["coverage"] == both.fit_report["coverage"]
    # the calibration: the calibrated ground's steady map moved where the lane holds are (v_ref 0.8-1.8 m/s,
    # |omega_ref| <= 0.8 rad/s), by more than a float's noise
    assert plain.calibration is not None and both.calibration is not None
    resp_plain, resp_both = plain.calibration.response, both.calibration.response
    lane = np.ix_([0], (resp_plain.v_ref >= 0.8) & (resp_plain.v_ref <= 1.8), np.abs(resp_plain.omega_ref) <= 0.8)
    moved = np.abs(resp_both.steady[lane] - resp_plain.steady[lane])
    assert moved.max() > 1e-3, moved.max()
    assert not np.array_equal(plain.calibration.command_gain[0], both.calibration.command_gain[0])
    # which logs fed what, in the profile (and its command line)
    assert plain.fit_report["logs"]["calibration_only"] == []
    logs_meta = both.fit_report["logs"]
    assert logs_meta["training"] == [str(train)] and logs_meta["calibration_only"] == [str(cal)]
    assert logs_meta["calibration_only_holds"][GROUNDS[0]] > 0 and logs_meta["calibration_only_holds"][GROUNDS[1]] == 0
    assert logs_meta["calibration_holds"][GROUNDS[0]] > plain.fit_report["logs"]["calibration_holds"][GROUNDS[0]]
    assert both.made_by is not None and f"--calibration-log {cal}" in both.made_by


@pytest.mark.slow(seconds=6)  # five refused trainings (each reads the logs first) and a 40 m drive
def test_a_bad_calibration_log_is_refused_in_one_line(logs: tuple[Path, Path], tmp_path: Path) -> None:
    train, cal = logs
    out = tmp_path / "p.npz"

    def refused(calibration: Path, *needles: str, data: Path = train) -> None:
        _one_line_refusal(["train", str(data), "--calibration-log", str(calibration), "-o", str(out), *FAST],
                          *needles, written=out)

    refused(_relabelled(cal, tmp_path / "husky.mcap", robot="husky"), "husky.mcap", "gpmppi/husky/state")
    refused(_relabelled(cal, tmp_path / "unlabelled.mcap", labels=False), "unlabelled.mcap", "no terrain labels")
    refused(train, "both as a training log and as a --calibration-log")
    text = tmp_path / "notes.mcap"
    text.write_text("not a log\n")
    refused(text, "notes.mcap", "MCAP")
    # a calibration log of a ground the GP is not trained on: refused, unless --terrain keeps only trained grounds
    tile_only = tmp_path / "tile.mcap"
    result = runner.invoke(app, ["dataset", "-o", str(tile_only), "--distance", "40", "-t", GROUNDS[1]])
    assert result.exit_code == 0, result.output
    _one_line_refusal(["train", str(tile_only), "--calibration-log", str(cal), "-o", str(out), *FAST],
                      "cal.mcap", repr(GROUNDS[0]), "--terrain", written=out)
    csv = tmp_path / "r.csv"
    csv.write_text("cmd_lin,cmd_ang,curr_lin,curr_ang,Grass_Lin_Error,Grass_Ang_Error\n1,0,1,0,0,0\n")
    refused(cal, "residual CSV", data=csv)
