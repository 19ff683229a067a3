"""The robot profile: one file from logs (GP, nominal model, terrain calibration), its format, the estimator reading
its calibration, `gpmppi train` writing it, the one `profile` setting, and every refusal in one line."""

from __future__ import annotations

import json
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from cached_models import shipped_model, synthetic_model
from conftest import FAST_TRAIN, PROFILE_GROUNDS
from test_terrain_bayes import _history
from typer.testing import CliRunner

from gpmppi.gp.model_file import DEFAULT_MODEL_PATH, GPModel, ModelFileError
from gpmppi.profile.response import SHIPPED_RESPONSE
from gpmppi.profile.terrain_calibration import TerrainCalibration
from gpmppi.terrain.estimator import make_estimator
from gpmppi.terrain.settings import EstimatorConfig
from services.launch.launch_file import LaunchFileError, check_profile_grounds, load_launch, profile_configs
from tools.cli import app
from tools.dataset import read_dataset, write_dataset
from tools.replay_live import LiveService, finalize

runner = CliRunner()
GROUNDS = PROFILE_GROUNDS  # the small dataset's (two grounds keep the file fast)
FAST = FAST_TRAIN  # `gpmppi train`'s settings for these tests: few points and iterations, no grid table


def _profile() -> GPModel:
    m = synthetic_model()
    m.robot, m.made_by = "jackal", "gpmppi train log.mcap -o p.npz"
    return m


def _rewrite_metadata(path: Path, **changes) -> None:
    """Rewrite `path`'s metadata entry with `changes` (and drop the calibration arrays when version is 1)."""
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = {**json.loads(str(arrays["metadata"][()])), **changes}
    if meta["version"] == 1:  # as version 1 wrote it: no robot, no calibration
        arrays = {k: v for k, v in arrays.items() if not k.startswith("cal_")}
        meta.pop("robot", None)
    arrays["metadata"] = np.array(json.dumps(meta))
    np.savez_compressed(path, **arrays)


def _one_line_refusal(args: list[str], *needles: str, written: Path | None = None) -> str:
    result = runner.invoke(app, args)
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2, (args, result.output)
    assert len(lines) == 1 and "Traceback" not in lines[0], lines
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    assert written is None or not written.exists()
    return lines[0]


# ---- the format --------------------------------------------------------------------------------------------------
def test_a_profile_round_trips_bit_equal_with_its_robot_and_calibration(tmp_path: Path) -> None:
    m = _profile()
    path = tmp_path / "p.npz"
    m.save(path)
    with zipfile.ZipFile(path) as z:
        assert {"cal_command_gain.npy", "cal_steady.npy", "cal_rate.npy"} <= set(z.namelist())
    r = GPModel.load(path)
    assert r.file_version == 2 and r.robot == "jackal" and r.made_by == m.made_by and r.source == str(path)
    assert r.calibration is not None and m.calibration is not None
    assert r.calibration.terrains == tuple(r.terrains)
    np.testing.assert_array_equal(r.calibration.command_gain, m.calibration.command_gain)
    for name in ("v_ref", "omega_ref", "steady", "rate"):
        np.testing.assert_array_equal(getattr(r.calibration.response, name), getattr(m.calibration.response, name))
    for name in ("theta", "train_x", "chol", "alpha", "lengthscale", "noise"):
        np.testing.assert_array_equal(getattr(r, name), getattr(m, name))


def test_the_calibration_is_stored_in_the_models_ground_order(tmp_path: Path) -> None:
    m = _profile()
    assert m.calibration is not None
    flipped = m.calibration.select(list(reversed(m.terrains)))
    m.calibration = flipped  # as a fit in another order would give it
    m.save(tmp_path / "p.npz")
    r = GPModel.load(tmp_path / "p.npz")
    assert r.calibration is not None and r.calibration.terrains == tuple(m.terrains)
    np.testing.assert_array_equal(r.calibration.command_gain[0], flipped.command_gain[-1])


def test_a_v1_file_loads_as_a_gp_and_the_estimator_refuses_it_in_one_line(tmp_path: Path) -> None:
    path = tmp_path / "old.npz"
    _profile().save(path)
    _rewrite_metadata(path, version=1)
    old = GPModel.load(path)
    assert old.file_version == 1 and old.calibration is None and old.robot == "jackal"
    with pytest.raises(ModelFileError) as err:
        make_estimator(old, EstimatorConfig())  # the defaults need the calibration
    assert str(err.value) == (f"{path} is a v1 GP model without a terrain calibration (an older format); refit it as "
                              f"a robot profile with `gpmppi train LOGS -o {path}`")
    # GP-only use, and explicit calibration files, still work on it
    make_estimator(old, EstimatorConfig(command_change="online", response="none"))
    gains = {t: (-0.01, -0.01) for t in old.terrains}
    make_estimator(old, EstimatorConfig(command_gains=gains, response_file=str(SHIPPED_RESPONSE)))


@pytest.mark.parametrize("version", [3, 0, "2"])
def test_an_unknown_version_is_refused_naming_it(tmp_path: Path, version: object) -> None:
    path = tmp_path / "new.npz"
    _profile().save(path)
    _rewrite_metadata(path, version=version)
    with pytest.raises(ModelFileError, match=f"format version {version!r}.*reads versions \\[1, 2\\]"):
        GPModel.load(path)


def test_an_incomplete_calibration_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "p.npz"
    _profile().save(path)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files if k != "cal_rate"}
    np.savez_compressed(path, **arrays)
    with pytest.raises(ModelFileError, match=r"terrain calibration is incomplete \(missing \['cal_rate'\]\)"):
        GPModel.load(path)


def test_the_shipped_profile_carries_a_calibration_of_its_grounds_and_names_what_made_it() -> None:
    m = shipped_model()
    assert m.file_version == 2 and m.robot == "jackal" and sorted(m.terrains) == ["asphalt", "grass", "tile"]
    assert m.calibration is not None and m.calibration.terrains == tuple(m.terrains)
    assert np.all(np.isfinite(m.calibration.command_gain)) and np.any(m.calibration.command_gain != 0)
    assert m.made_by is not None and "gpmppi train" in m.made_by and "gpmppi dataset" in m.made_by
    assert Path(m.source or "") == DEFAULT_MODEL_PATH


# ---- the estimator reads the profile's calibration ----------------------------------------------------------------
def _twin() -> GPModel:
    """The synthetic model with tile's GP made grass's: only the command-change gains tell the two apart."""
    model = synthetic_model()
    twin = replace(model, alpha=model.alpha.copy(), chol=model.chol.copy(), lengthscale=model.lengthscale.copy(),
                   outputscale=model.outputscale.copy(), noise=model.noise.copy(), _grid=None)
    for a in (twin.alpha, twin.chol, twin.lengthscale, twin.outputscale, twin.noise):
        a[4:6] = a[2:4]
    return twin


def _with_gains(model: GPModel, gains: np.ndarray) -> GPModel:
    assert model.calibration is not None
    out = replace(model, _grid=None)
    out.calibration = TerrainCalibration(model.calibration.terrains, gains, model.calibration.response)
    return out


def test_the_estimator_takes_the_gains_from_the_profile_and_they_matter() -> None:
    twin = _twin()
    gains = np.array([[-0.01, -0.01], [-0.04, -0.02], [-0.07, -0.04]])  # asphalt, grass, tile
    cfg = EstimatorConfig(response="none")  # command_change per_terrain, gains None: the profile's
    noise = float(np.sqrt(twin.noise.mean()))
    rows = _history(twin, 2, 60, seed=9, noise=noise, gain=tuple(gains[2]))
    calibrated = make_estimator(_with_gains(twin, gains), cfg)
    zeroed = make_estimator(_with_gains(twin, 0 * gains), cfg)
    for row in rows:
        calibrated.observe(*row)
        zeroed.observe(*row)
    w, w0 = calibrated.estimate().weights, zeroed.estimate().weights
    assert w[2] > 0.9  # tile, told from grass by its gain alone
    assert abs(w0[1] - w0[2]) < 1e-5  # without the gains the two are one ground
    # an explicit command_gains setting still wins over the profile's
    override = make_estimator(_with_gains(twin, 0 * gains), EstimatorConfig(
        response="none", command_gains={t: tuple(g) for t, g in zip(twin.terrains, gains, strict=True)}))
    for row in rows:
        override.observe(*row)
    np.testing.assert_allclose(override.estimate().weights, w)


def test_the_estimator_takes_the_response_from_the_profile() -> None:
    model = synthetic_model()
    for a in (model.alpha, model.chol, model.lengthscale, model.outputscale, model.noise):
        a[2:4], a[4:6] = a[0:2], a[0:2]  # one GP for every ground: only the response tells them apart
    model = replace(model, _grid=None)
    assert model.calibration is not None
    r = model.calibration.response
    assert make_estimator(model, EstimatorConfig())._response is r  # noqa: SLF001 - the filter runs on the profile's
    flat = replace(model, _grid=None)
    flat.calibration = TerrainCalibration(model.calibration.terrains, model.calibration.command_gain,
                                          replace(r, steady=np.zeros_like(r.steady),
                                                  rate=np.full_like(r.rate, 0.5)))
    u = np.array([1.0, 1.0])
    held = np.r_[0.0, 0.0, 0.0, r.steady_at(u)[2]]  # tile's steady state under the held command
    weights = []
    for m in (model, flat):
        e = make_estimator(m, EstimatorConfig(command_change="none", gp_max_speed_gap=float("inf")))
        for _ in range(60):
            e.observe(held, u, held)
        weights.append(e.estimate().weights)
    assert weights[0][2] > 0.9, weights  # the profile's map: tile
    np.testing.assert_allclose(weights[1], 1 / 3, atol=0.05)  # a zeroed map and one rate: no ground stands out


# ---- `gpmppi train` writes the profile ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def dataset(grounds_log: Path) -> Path:
    """300 m on each of GROUNDS (made once a run, shared with tests/test_train_calibration_log.py: conftest.py)."""
    return grounds_log


@pytest.mark.slow(seconds=7)  # `gpmppi train` on a log (once a run: the profile is shared, tests/conftest.py)
def test_train_writes_a_whole_profile_from_a_log(dataset: Path, grounds_profile: Path) -> None:
    """`gpmppi train LOG -o OUT` + FAST (run by the `grounds_profile` fixture, which fails where it does not exit 0)."""
    out = grounds_profile
    p = GPModel.load(out)
    assert p.file_version == 2 and p.robot == "jackal" and p.terrains == GROUNDS
    assert p.calibration is not None and p.calibration.terrains == tuple(GROUNDS)
    assert np.all(np.isfinite(p.calibration.command_gain)) and np.all(p.calibration.command_gain[:, 0] < 0)
    assert p.made_by is not None and p.made_by.startswith(f"gpmppi train {dataset} -o {out} --robot jackal")
    make_estimator(p, EstimatorConfig())  # the defaults run on it
    # the novelty test's calibration, fitted on the same logs (gpmppi/terrain/novelty.py)
    assert p.novelty is not None and "fitted on the logs" in p.novelty.source and min(p.novelty.spread) > 0
    # and its free-run channel's (gpmppi/terrain/free_run.py): the level a quantile of the logs' statistic
    free = p.novelty.free_run
    assert free is not None and "fitted on the logs" in free.source and min(free.spread) > 0 and free.enter > 0
    coverage = (p.fit_report or {})["coverage"]  # the fit's coverage report travels with it
    assert [c["terrain"] for c in coverage] == GROUNDS and all(c["held_commands"] > 0 for c in coverage)


@pytest.mark.slow(seconds=7)  # `gpmppi train` on three logs
def test_train_fits_one_profile_from_several_logs_one_ground_each(dataset: Path, tmp_path: Path) -> None:
    """A calibration drive records one log per ground (and per resumed run): train takes them all at once, and no
    one-step pair spans two logs (each log's series keeps its own segments)."""
    from tools.train_data import read_log_series, read_logs_series

    runs = read_dataset(dataset)
    logs = []
    for ground in GROUNDS:
        logs.append(tmp_path / f"{ground}.mcap")
        write_dataset(logs[-1], {ground: runs[ground][0]})
    merged = read_logs_series(logs + [logs[0]], 0.1, None, None)  # a ground's second run appended to its first
    first = read_log_series(logs[0], 0.1, None, None)[GROUNDS[0]]
    assert sorted(merged) == GROUNDS
    assert len(merged[GROUNDS[0]]["v"]) == 2 * len(first["v"])
    segs = merged[GROUNDS[0]]["seg"]
    assert set(segs[: len(first["seg"])]).isdisjoint(segs[len(first["seg"]):])
    out = tmp_path / "p.npz"
    result = runner.invoke(app, ["train", *map(str, logs), "-o", str(out), *FAST])
    assert result.exit_code == 0, result.output
    p = GPModel.load(out)
    assert p.terrains == GROUNDS and p.calibration is not None and p.calibration.terrains == tuple(GROUNDS)
    assert p.made_by is not None and p.made_by.startswith(f"gpmppi train {logs[0]} {logs[1]} -o {out}")
    csv = tmp_path / "r.csv"
    csv.write_text("a\n1\n")
    result = runner.invoke(app, ["train", str(logs[0]), str(csv), "-o", str(tmp_path / "q.npz"), *FAST])
    assert result.exit_code == 2 and "not both" in result.output and not (tmp_path / "q.npz").exists()


def _relabelled(dataset: Path, out: Path, robot: str = "jackal", zigzag: int = 0, labels: bool = True) -> Path:
    """The dataset written again: under another robot name, with every command nudged every `zigzag` ticks (no
    command is held longer), or with no terrain labels."""
    runs = {t: rs[0] for t, rs in read_dataset(dataset).items()}
    if zigzag:
        for r in runs.values():
            r.command[:, 0] += 0.002 * (-1.0) ** (np.arange(len(r.command)) // zigzag)
    write_dataset(out, runs, robot=robot)
    if not labels:
        from services.recording.mcap_io import read_messages
        from services.recording.mcap_writer import McapWriter

        kept = [(k, m) for k, _, m in read_messages(out) if not k.endswith("terrain/label")]
        out.unlink()
        with McapWriter(out) as w:
            for k, m in kept:
                w.write(k, m, log_time_ns=m.header.stamp_ns)
    return out


def test_train_refuses_a_log_of_another_robot_naming_its_keys(dataset: Path, tmp_path: Path) -> None:
    log = _relabelled(dataset, tmp_path / "husky.mcap", robot="husky")
    out = tmp_path / "p.npz"
    _one_line_refusal(["train", str(log), "-o", str(out), *FAST], "'jackal'", "gpmppi/husky/state", "--robot",
                      written=out)


def test_train_refuses_a_log_without_terrain_labels(dataset: Path, tmp_path: Path) -> None:
    log = _relabelled(dataset, tmp_path / "unlabelled.mcap", labels=False)
    out = tmp_path / "p.npz"
    _one_line_refusal(["train", str(log), "-o", str(out), *FAST], "no terrain labels", "--terrain", written=out)


@pytest.mark.parametrize("zigzag", [1, 15], ids=["never-held", "held-1.5s"])
def test_train_refuses_a_log_without_held_commands_naming_the_ground(dataset: Path, tmp_path: Path,
                                                                    zigzag: int) -> None:
    """Never held: the coverage check refuses before the GP fit; held only 1.5 s: the calibration fit refuses
    (CalibrationDataError: its steady map needs commands held 2 s and more)."""
    log = _relabelled(dataset, tmp_path / "jittery.mcap", zigzag=zigzag)
    out = tmp_path / "p.npz"
    _one_line_refusal(["train", str(log), "-o", str(out), *FAST], "ground 'grass'", "hold commands", written=out)


# ---- the one setting: launch files, evaluate, replay --------------------------------------------------------------
def test_a_launch_files_profile_reaches_the_planner_and_terrain_services(tmp_path: Path) -> None:
    _profile().save(tmp_path / "robot.npz")
    (tmp_path / "launch.yaml").write_text(
        "profile: robot.npz\nservices:\n  - name: sim\n    config: {terrain: tile}\n  - name: planner\n"
        "  - name: terrain\n  - name: egress\n")
    launch, _ = load_launch(tmp_path / "launch.yaml")
    assert launch.profile == str((tmp_path / "robot.npz").resolve())
    configs = {e.name: e.config for e in profile_configs(launch, launch.services)}
    assert configs["planner"]["model_file"] == configs["terrain"]["model_file"] == launch.profile
    assert "model_file" not in configs["sim"] and "model_file" not in configs["egress"]
    check_profile_grounds(launch, tmp_path / "launch.yaml")


def test_a_launch_file_driving_a_ground_the_profile_lacks_is_refused_in_one_line(tmp_path: Path) -> None:
    _profile().save(tmp_path / "robot.npz")
    bad = tmp_path / "launch.yaml"
    bad.write_text("profile: robot.npz\nservices:\n  - name: sim\n    config: {terrain: sand}\n  - name: planner\n")
    launch, _ = load_launch(bad)
    with pytest.raises(LaunchFileError, match=r"ground 'sand'.*\['asphalt', 'grass', 'tile'\]"):
        check_profile_grounds(launch, bad)
    line = _one_line_refusal(["launch", str(bad), "--duration", "1"], "'sand'", "robot.npz")
    assert str(bad) in line


def test_a_launch_file_naming_a_v1_model_for_the_terrain_service_is_refused_before_it_starts(tmp_path: Path) -> None:
    _profile().save(tmp_path / "old.npz")
    _rewrite_metadata(tmp_path / "old.npz", version=1)
    bad = tmp_path / "launch.yaml"
    bad.write_text("profile: old.npz\nservices:\n  - name: terrain\n  - name: planner\n")
    with pytest.raises(LaunchFileError, match="v1 GP model without a terrain calibration"):
        check_profile_grounds(load_launch(bad)[0], bad)
    # GP-only use of it is fine: the paper's estimator, or the Bayes filter without the calibration
    bad.write_text("profile: old.npz\nservices:\n  - name: terrain\n    config: {estimator: {command_change: "
                   "online, response: none}}\n  - name: planner\n")
    check_profile_grounds(load_launch(bad)[0], bad)


def test_evaluate_refuses_a_profile_of_grounds_its_plant_lacks(tmp_path: Path) -> None:
    other = synthetic_model(terrains=("gravel", "mulch"))
    other.save(tmp_path / "other.npz")
    _one_line_refusal(["evaluate", "tracking", "--profile", str(tmp_path / "other.npz"), "--quick"],
                      "ground 'gravel'", "['gravel', 'mulch']", "--terrain-file")
    # the same profile named once, in the launch file evaluate runs the deployed path of
    (tmp_path / "launch.yaml").write_text("profile: other.npz\nservices:\n  - name: planner\n")
    _one_line_refusal(["evaluate", "tracking", "--launch-file", str(tmp_path / "launch.yaml"), "--quick"],
                      "ground 'gravel'", str(tmp_path / "other.npz"))


def test_replay_gives_its_profile_to_the_replaced_planner_and_terrain(tmp_path: Path) -> None:
    from services.recording.player_log import RunInfo

    _profile().save(tmp_path / "robot.npz")
    live = [LiveService("planner", "planner", {"model_file": "/recorded/default_gp_model.npz"}, True),
            LiveService("terrain", "terrain", {}, True)]
    info = RunInfo(attachments={"model/default_gp_model.npz": DEFAULT_MODEL_PATH.read_bytes()})
    finalize(live, info, "jackal", "tcp/127.0.0.1:1", tmp_path, tmp_path / "robot.npz")
    assert [s.config["model_file"] for s in live] == [str((tmp_path / "robot.npz").resolve())] * 2
    (tmp_path / "junk.npz").write_text("no")
    with pytest.raises(ModelFileError, match="junk.npz"):
        finalize(live, info, "jackal", "tcp/127.0.0.1:1", tmp_path, tmp_path / "junk.npz")


def test_the_terrain_service_refuses_a_v1_model_in_one_line_before_it_joins(tmp_path: Path, capsys) -> None:
    from services.terrain import Settings, run

    _profile().save(tmp_path / "old.npz")
    _rewrite_metadata(tmp_path / "old.npz", version=1)
    assert run(Settings(model_file=str(tmp_path / "old.npz"))) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "v1 GP model without a terrain calibration" in err[0] and "gpmppi train" in err[0]
