"""The terrain service learns a ground while it runs (real Zenoh on loopback, the service in its own process): a
GroundLearn request, the steps, the fit in the background, the profile on disk, a ModelUpdate, and weights naming
the learned ground. And a fit with too little data adds nothing and says why."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from test_online_ground import _model, drive
from zenoh_helpers import Collector, ServiceProcess, client, free_port, router, settings, wait_for

from gpmppi.gp.model_file import GPModel
from gpmppi.gp.online_ground import LearnSettings
from gpmppi.gp.profile_store import file_sha256, save_profile
from gpmppi.terrain.learning import FitJob
from schemas import BaseCommand, GroundLearn, ModelUpdate, State, TerrainWeights, decode, encode
from services.terrain_learning import run_fit


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
                state = State(x=x[0], y=x[1], theta=x[2], v=x[3], omega=x[4])
                state.header.stamp_ns = t_ns
                state_pub.put(encode(state))
                cmd = BaseCommand(v=u[0], omega=u[1])
                cmd.header.stamp_ns = t_ns
                cmd_pub.put(encode(cmd))
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
