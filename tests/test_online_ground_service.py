"""The terrain service learns a ground while it runs (real Zenoh on loopback, the service in its own process): a
GroundLearn request, the steps, the fit in the background, the profile on disk, a ModelUpdate, and weights naming
the learned ground. And a fit with too little data adds nothing and says why."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from test_online_ground import _model, drive
from zenoh_helpers import (
    Collector,
    ServiceProcess,
    client,
    free_port,
    put_state_and_base_command,
    router,
    settings,
    wait_for,
)

from gpmppi.gp.model_file import GPModel
from gpmppi.gp.online_ground import LearnSettings
from gpmppi.gp.profile_store import file_sha256, save_profile
from gpmppi.terrain.learning import FitJob
from schemas import GroundLearn, ModelUpdate, State, TerrainWeights, decode, encode
from services.terrain_learning import run_fit


@pytest.mark.slow(seconds=10)  # a terrain service that collects a drive and fits a ground in its own process
def test_terrain_service_learns_a_ground_and_announces_the_new_model(tmp_path: Path) -> None:
    profile = tmp_path / "robot.npz"
    save_profile(_model(), profile)
    learn = {"steps": 120, "min_samples": 100, "max_points": 40}
    port = free_port()
    with router(port):
        observer = client(port)
        col = Collector(observer, "gpmppi/r1/**")
        proc = ServiceProcess("terrain", settings("terrain", port, command_wait_s=0.05, model_file=str(profile),
                                                  learn=learn), tmp_path)
        try:
            feeder = client(port)
            state_pub = feeder.declare_publisher("gpmppi/r1/state")
            cmd_pub = feeder.declare_publisher("gpmppi/r1/base/cmd")
            learn_pub = feeder.declare_publisher("gpmppi/r1/terrain/learn")
            rows = iter(drive(_model(), 2000, seed=1))
            t_ns = time.time_ns()

            def step() -> None:
                nonlocal t_ns
                x, u, _ = next(rows)
                put_state_and_base_command(state_pub, cmd_pub, x, u, t_ns)
                t_ns += 100_000_000

            def weights() -> list[TerrainWeights]:
                return [decode(TerrainWeights, p) for _, p, _ in col.on("gpmppi/r1/terrain/weights")]

            assert wait_for(lambda: (step(), any(w.solver_ok for w in weights()))[1], 60.0, step=0.02), \
                proc.log()[-3000:]
            learn_pub.put(encode(GroundLearn(name="dune")))

            def updated() -> bool:
                step()
                return bool(col.on("gpmppi/r1/model")) and weights()[-1].names[-1] == "dune"

            assert wait_for(updated, 90.0, step=0.02), proc.log()[-3000:]
            update = decode(ModelUpdate, col.on("gpmppi/r1/model")[0][1])
            assert update.version == 1 and update.learned == "dune" and update.samples >= 120
            assert update.grounds == [*_model().terrains, "dune"] and update.path == str(profile)
            assert file_sha256(profile) == update.sha256
            assert GPModel.load(profile).terrains[-1] == "dune"  # on disk: a restart keeps it
            assert "fitting ground 'dune'" in proc.log() and "model version 1" in proc.log()
            assert proc.stop() == 0, proc.log()[-3000:]
            # a restarted terrain service comes up with the learned ground (it is in the profile on disk)
            seen = len(weights())
            (tmp_path / "again").mkdir()
            proc = ServiceProcess("terrain", settings("terrain", port, command_wait_s=0.05, model_file=str(profile),
                                                      learn=learn), tmp_path / "again")
            assert wait_for(lambda: (step(), len(weights()) > seen and weights()[-1].names[-1] == "dune")[1], 60.0,
                            step=0.02), proc.log()[-3000:]
            feeder.close()
        finally:
            code = proc.stop()
            observer.close()
    assert code == 0, proc.log()[-3000:]


def test_a_fit_with_too_little_data_adds_nothing_and_says_why(tmp_path: Path) -> None:
    profile = tmp_path / "robot.npz"
    save_profile(_model(), profile)
    before = profile.read_bytes()
    rows = drive(_model(), 40, seed=2)
    x = np.array([[u[0], u[1], s[3], s[4]] for s, u, _ in rows])
    job = FitJob(_model(), "dune", x, np.zeros((len(x), 2)), np.zeros((len(x), 2)), LearnSettings(min_samples=100))
    out = run_fit(job, str(profile))
    assert out.error == ("ground 'dune': 40 steps collected, at least 100 needed (10 s of driving on it); not added")
    assert profile.read_bytes() == before and out.sha256 == ""


def test_the_recorder_attaches_each_announced_profile_and_replay_finds_it(tmp_path: Path) -> None:
    from services.recording.player_log import read_run_info
    from tools.replay_live import LiveService, finalize

    profile = tmp_path / "robot.npz"
    sha = save_profile(_model(), profile)
    gone = ModelUpdate(version=2, path=str(tmp_path / "gone.npz"), sha256="0" * 64, grounds=["x"])
    update = ModelUpdate(version=1, path=str(profile), sha256=sha, grounds=list(_model().terrains))
    path = tmp_path / "run.mcap"
    port = free_port()
    with router(port):
        observer = client(port)
        col = Collector(observer, "gpmppi/r1/health/**")
        rec = ServiceProcess("recorder", settings("recorder", port, path=str(path)), tmp_path)
        try:
            assert wait_for(lambda: bool(col.on("gpmppi/r1/health/recorder")), 15.0), rec.log()
            outside = client(port)
            pub = outside.declare_publisher("gpmppi/r1/model")
            pub.put(encode(update))
            pub.put(encode(gone))
            assert wait_for(lambda: "gone.npz (version 2) not attached" in rec.log(), 15.0), rec.log()[-2000:]
            outside.close()
        finally:
            assert rec.stop() == 0
            observer.close()
    info = read_run_info([path])
    assert info.attachments[f"learned/{sha}.npz"] == profile.read_bytes()
    assert [n for n in info.attachments if n.startswith("learned/")] == [f"learned/{sha}.npz"]
    # replay: the planner gets a folder holding the recording's copy by its hash, which the swap takes first
    planner = LiveService("planner", "planner", {"model_file": str(profile)}, False)
    finalize([planner], info, "r1", "tcp/127.0.0.1:7447", tmp_path)
    assert (Path(planner.config["learned_dir"]) / f"{sha}.npz").read_bytes() == profile.read_bytes()


def test_the_planner_swap_loads_the_announced_model_on_a_thread_and_refuses_other_bytes(tmp_path: Path) -> None:
    from test_online_ground import SETTINGS, samples

    from gpmppi.gp.online_ground import learn_ground
    from gpmppi.mppi.config import PlannerConfig
    from services.model_swap import ModelSwap

    new, _ = learn_ground(_model(), samples(_model(), 250), settings=SETTINGS)
    (tmp_path / "store").mkdir()
    sha = save_profile(new, tmp_path / "store" / "x.npz")
    (tmp_path / "store" / "x.npz").rename(tmp_path / "store" / f"{sha}.npz")
    swap = ModelSwap(PlannerConfig(samples=64, horizon=20), search_dir=str(tmp_path / "store"))
    update = ModelUpdate(version=1, path=str(tmp_path / "moved.npz"), sha256=sha, grounds=list(new.terrains))
    assert "model version 1" in (swap.offer(update) or "")
    assert swap.offer(update) is None  # the same bytes: loading already
    out: list = []

    def taken() -> bool:
        if (ready := swap.take()) is not None:
            out.append(ready)
        return bool(out)

    assert wait_for(taken, 30.0, step=0.05)
    ready = out.pop()
    assert not ready.error and ready.model.terrains == new.terrains and ready.planner is not None
    assert swap.version == 1 and swap.sha256 == sha and swap.offer(update) is None  # planned with now
    wrong = ModelUpdate(version=2, path=str(tmp_path / "store" / f"{sha}.npz"), sha256="f" * 64, grounds=["x"])
    swap.offer(wrong)
    assert wait_for(taken, 30.0, step=0.05)
    assert "not taken" in out[-1].error and "is not the announced" in out[-1].error and swap.version == 1
    swap.close()


def test_the_fit_keeps_its_steps_as_a_log_that_gpmppi_train_reads(tmp_path: Path) -> None:
    from test_online_ground import SETTINGS, samples

    from gpmppi.gp.train import prepare_from_series
    from services.terrain_learning import steps_log_path
    from tools.train_data import read_log_series

    profile = tmp_path / "robot.npz"
    save_profile(_model(), profile)
    s = samples(_model(), 250)
    x, y, du = s.arrays()
    out = run_fit(FitJob(_model(), "dune", x, y, du, SETTINGS, np.stack(s.steps)), str(profile))
    assert not out.error and GPModel.load(profile).terrains[-1] == "dune"
    log = steps_log_path(profile, "dune")
    assert log == tmp_path / "robot.dune.mcap" and [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    series = read_log_series(log, 0.1, None, None)
    assert list(series) == ["dune"] and len(series["dune"]["v"]) == 2 * len(x)
    sets, _, _ = prepare_from_series(series, 0.1, theta=_model().theta, edd5={"dune": np.zeros(5)})
    np.testing.assert_allclose(sets["dune"].x, x, atol=1e-9)  # the same steps, one pair each
    np.testing.assert_allclose(sets["dune"].residual, y, atol=1e-9)


def test_the_planner_service_takes_a_new_model_version_between_plans(tmp_path: Path) -> None:
    import math

    from test_online_ground import SETTINGS, samples
    from zenoh_helpers import matched_publisher

    from gpmppi.gp.online_ground import learn_ground
    from schemas import Header, Plan

    profile = tmp_path / "robot.npz"
    save_profile(_model(), profile)
    new, _ = learn_ground(_model(), samples(_model(), 250), "dune", settings=SETTINGS)
    learned = tmp_path / "learned.npz"
    sha = save_profile(new, learned)
    cfg = settings("planner", port := free_port(), compensate_delay=False, model_file=str(profile),
                   planner={"samples": 64, "horizon": 20, "backend": "cpu"})
    with router(port):
        observer = client(port)
        col = Collector(observer, "gpmppi/r1/**")
        proc = ServiceProcess("planner", cfg, tmp_path)
        try:
            assert wait_for(lambda: bool(col.on("gpmppi/r1/health/planner")), 120.0), proc.log()[-3000:]
            state_pub = matched_publisher(observer, "gpmppi/r1/state")
            model_pub = observer.declare_publisher("gpmppi/r1/model")
            weights_pub = observer.declare_publisher("gpmppi/r1/terrain/weights")
            k = 0

            def plans() -> list[Plan]:
                return [decode(Plan, p) for _, p, _ in col.on("gpmppi/r1/plan")]

            def step() -> None:
                nonlocal k
                x = np.array([20.0, 0.1 * k, math.pi / 2, 1.0, 0.05])
                k += 1
                state_pub.put(encode(State(x=x[0], y=x[1], theta=x[2], v=x[3], omega=x[4],
                                           header=Header(stamp_ns=time.time_ns()))))
                time.sleep(0.05)

            assert wait_for(lambda: (step(), bool(plans()))[1], 30.0), proc.log()[-3000:]
            assert plans()[-1].model_version == 0 and len(plans()[-1].terrain_weights) == 3
            model_pub.put(encode(ModelUpdate(version=1, path=str(learned), sha256=sha, grounds=list(new.terrains),
                                             learned="dune", samples=250)))
            assert wait_for(lambda: (step(), plans()[-1].model_version == 1)[1], 30.0), proc.log()[-3000:]
            w = TerrainWeights(names=list(new.terrains), weights=[0.05, 0.05, 0.1, 0.8])
            weights_pub.put(encode(w))
            assert wait_for(lambda: (step(), plans()[-1].terrain_weights == [0.05, 0.05, 0.1, 0.8])[1], 30.0), \
                proc.log()[-3000:]
            assert "planning with model version 1: grounds" in proc.log()
            assert "weights_invalid" not in str([h for _, h, _ in col.on("gpmppi/r1/health/planner")][-1:])
        finally:
            code = proc.stop()
            observer.close()
    assert code == 0, proc.log()[-3000:]


def test_a_full_disk_while_the_fit_saves_leaves_the_old_profile_and_nothing_else(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    """The fit's whole save (the steps log, then the profile) on a disk that fills up at the profile: one line that
    says so, the old profile byte-identical, and no temporary file or steps log of the ground it did not gain."""
    import errno

    from test_online_ground import SETTINGS, samples

    import gpmppi.gp.model_file as model_file

    profile = tmp_path / "robot.npz"
    save_profile(_model(), profile)
    before = profile.read_bytes()
    s = samples(_model(), 250)
    x, y, du = s.arrays()

    def disk_full(f, **arrays) -> None:  # noqa: ANN001, ANN003 - np.savez_compressed's form
        f.write(b"PK\x03\x04 half an archive")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(model_file.np, "savez_compressed", disk_full)
    out = run_fit(FitJob(_model(), "dune", x, y, du, SETTINGS, np.stack(s.steps)), str(profile))
    assert out.error == (f"learned ground 'dune' not saved to {profile}: No space left on device; the profile there "
                         "is unchanged") and out.sha256 == ""
    assert profile.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["robot.npz"]
