"""Learning a new ground online (gpmppi/gp/online_ground.py): the learner recovers a synthetic ground's residual, leaves
the trained grounds untouched, refuses too little data, and the estimator then identifies the learned ground."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest
from cached_models import synthetic_model

from gpmppi.gp.grid_table import grid_axes, predict_dense
from gpmppi.gp.model_file import GPModel
from gpmppi.gp.online_ground import (
    GroundSamples,
    LearnSettings,
    TooLittleData,
    implied_steady,
    learn_ground,
    model_version,
    next_name,
)
from gpmppi.models.dynamic_unicycle import velocity_step_exact
from gpmppi.profile.response import TerrainResponse
from gpmppi.profile.terrain_calibration import TerrainCalibration
from gpmppi.terrain.estimator import make_estimator
from gpmppi.terrain.settings import EstimatorConfig

SETTINGS = LearnSettings(min_samples=200, max_points=80, seed=0)


@lru_cache(maxsize=1)
def _model() -> GPModel:
    """A synthetic profile whose calibration fits its own world: each ground's steady response is the one its
    one-step model settles to, and no command-change gain (the synthetic steps have none)."""
    model = synthetic_model(n_train=60, nodes=6)
    r = model.require_calibration().response
    steady = np.stack([implied_steady(model, m, r.v_ref, r.omega_ref) for m in range(model.n_terrains)])
    model.calibration = TerrainCalibration(r.terrains, np.zeros((model.n_terrains, 2)),
                                           TerrainResponse(r.v_ref, r.omega_ref, r.terrains, steady, r.rate))
    return model


def ground_residual(x: np.ndarray) -> np.ndarray:
    """The synthetic new ground's residual (N, 2) at GP inputs x (N, 4): smooth, and far from every trained one."""
    return np.column_stack([0.05 * np.tanh(x[:, 0] - x[:, 2]) - 0.03, -0.03 * np.sin(x[:, 1]) + 0.01 * x[:, 3]])


def drive(model: GPModel, steps: int, seed: int, noise: float = 0.003, residual=ground_residual  # noqa: ANN001
          ) -> list[tuple[np.ndarray, ...]]:
    """(state, command, next state) steps on a ground of `residual` (default: the new one), commands a smooth random
    walk."""
    rng = np.random.default_rng(seed)
    u = np.array([1.0, 0.0])
    x = np.array([0.0, 0.0, 0.0, 1.0, 0.0])
    rows = []
    for _ in range(steps):
        u = np.clip(u + rng.normal(0, [0.15, 0.3]), [0.1, -1.5], [1.9, 1.5])
        pv, pw = velocity_step_exact(model.theta, x[3:4].copy(), x[4:5].copy(), u[0:1].copy(), u[1:2].copy(),
                                     model.dt)
        r = residual(np.array([[u[0], u[1], x[3], x[4]]]))[0]
        x1 = x.copy()
        x1[3:5] = [pv[0] + r[0] + noise * rng.normal(), pw[0] + r[1] + noise * rng.normal()]
        rows.append((x, u.copy(), x1))
        x = x1
    return rows


def samples(model: GPModel, steps: int, seed: int = 0) -> GroundSamples:
    s = GroundSamples(model.theta, model.dt)
    for row in drive(model, steps, seed):
        s.add(*row)
    return s


def test_learner_recovers_the_grounds_residual_and_keeps_the_trained_ones() -> None:
    model = _model()
    new, report = learn_ground(model, samples(model, 300), settings=SETTINGS)
    assert new.terrains == [*model.terrains, "new-1"] and report.name == "new-1"
    # held-out steps of the same ground (another seed): the learned GP's mean against the true residual
    x = np.array([[u[0], u[1], s[3], s[4]] for s, u, _ in drive(model, 200, seed=9)])
    mean, var = predict_dense(new, x)
    truth = ground_residual(x)
    err = np.sqrt(np.mean((mean[:, -2:] - truth) ** 2, axis=0))
    assert np.all(err < 0.25 * np.sqrt(np.mean(truth**2, axis=0))), (err, report.line())
    assert np.all(err < np.sqrt(np.mean((mean[:, :2] - truth) ** 2, axis=0)))  # better than a trained ground
    old_mean, old_var = predict_dense(model, x)
    np.testing.assert_allclose(mean[:, :-2], old_mean, atol=1e-12)  # the trained grounds are untouched
    np.testing.assert_allclose(var[:, :-2], old_var, atol=1e-12)
    # the grid table got the new tasks' channels at its nodes: the exact GP there, to the table's quantization
    g = new.grid()
    nodes = np.stack(np.meshgrid(*grid_axes(g.lo, g.hi, g.dims), indexing="ij"), axis=-1).reshape(-1, 4)
    exact_m, exact_v = predict_dense(new, nodes)
    table = g.table.reshape(len(nodes), -1)
    t = new.n_tasks
    np.testing.assert_allclose(table[:, :t], exact_m, atol=1e-9)
    np.testing.assert_allclose(table[:, t:], exact_v, atol=1e-9)
    assert new.calibration is not None and new.calibration.terrains[-1] == "new-1"


def test_fitted_hyperparameters_also_recover_it() -> None:
    model = _model()
    fitted = LearnSettings(min_samples=200, max_points=60, hyperparameters="fitted", iters=30)
    new, _ = learn_ground(model, samples(model, 250), "mud", settings=fitted)
    x = np.array([[u[0], u[1], s[3], s[4]] for s, u, _ in drive(model, 200, seed=9)])
    truth = ground_residual(x)
    err = np.sqrt(np.mean((predict_dense(new, x)[0][:, -2:] - truth) ** 2, axis=0))
    assert new.terrains[-1] == "mud" and np.all(err < 0.25 * np.sqrt(np.mean(truth**2, axis=0)))


def test_too_little_data_is_refused_in_one_line() -> None:
    model = _model()
    with pytest.raises(TooLittleData, match=r"120 steps collected, at least 200 needed .*not added") as e:
        learn_ground(model, samples(model, 120), settings=SETTINGS)
    assert "\n" not in str(e.value)
    standing = GroundSamples(model.theta, model.dt)
    for _ in range(250):
        standing.add(np.zeros(5), np.zeros(2), np.zeros(5))
    with pytest.raises(TooLittleData, match="span 0.000 m/s of forward speed"):
        learn_ground(model, standing, settings=SETTINGS)
    with pytest.raises(TooLittleData, match="use 1-64 letters"):
        learn_ground(model, samples(model, 250), "../up", settings=SETTINGS)
    with pytest.raises(TooLittleData, match="already in the profile"):
        learn_ground(model, samples(model, 250), "grass", settings=SETTINGS)


def test_estimator_identifies_the_learned_ground() -> None:
    model = _model()
    new, _ = learn_ground(model, samples(model, 300), settings=SETTINGS)
    assert next_name(new) == "new-2" and model_version(model) == 0 and model_version(new) == 1
    assert new.fit_report["learned"][0]["ground"] == "new-1"
    est = make_estimator(new, EstimatorConfig())  # the default filter: the learned calibration's gain and response
    for row in drive(model, 150, seed=5):
        est.observe(*row)
    w = est.estimate().weights
    assert w[-1] >= 0.8, w
    # and a trained ground is still itself, not the learned one
    est = make_estimator(new, EstimatorConfig())
    for row in drive(model, 150, seed=6, residual=lambda x: predict_dense(model, x)[0][:, 2:4]):
        est.observe(*row)
    w = est.estimate().weights
    assert w[1] >= 0.8, w


def test_a_failing_write_leaves_the_old_profile_byte_identical(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    import errno

    import gpmppi.gp.model_file as model_file
    from gpmppi.gp.profile_store import file_sha256, load_checked, save_profile

    path = tmp_path / "robot.npz"
    sha = save_profile(_model(), path)
    before = path.read_bytes()
    new, _ = learn_ground(_model(), samples(_model(), 250), settings=SETTINGS)

    def disk_full(f, **arrays) -> None:  # noqa: ANN001, ANN003 - np.savez_compressed's form
        f.write(b"PK\x03\x04 half an archive")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(model_file.np, "savez_compressed", disk_full)
    with pytest.raises(OSError, match="No space left"):
        save_profile(new, path)
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["robot.npz"]
    monkeypatch.undo()
    new_sha = save_profile(new, path)
    assert new_sha == file_sha256(path) != sha
    assert load_checked(path, new_sha).terrains[-1] == "new-1"
    with pytest.raises(model_file.ModelFileError, match="is not the announced"):
        load_checked(path, sha)


def test_the_planner_cycle_takes_the_learned_model_between_plans() -> None:
    from gpmppi.mppi.config import PlannerConfig
    from gpmppi.mppi.cycle import Planned, PlannerCycle
    from gpmppi.mppi.cycle_config import CycleConfig
    from gpmppi.mppi.planner import Planner
    from gpmppi.tasks import LaneTask

    model = _model()
    new, _ = learn_ground(model, samples(model, 250), settings=SETTINGS)
    config = PlannerConfig(samples=64, horizon=20, seed=3)
    lane = LaneTask(np.array([[0.0, 0.0], [100.0, 0.0]]), half_width=1.0, closed=False)
    cycle = PlannerCycle(Planner(config, model), lane, CycleConfig(compensate_delay=False), model.n_terrains,
                         model.terrains, clock=lambda: 0.0)
    x = np.array([0.0, 0.0, 0.0, 1.0, 0.0])
    t_ns = 1_000_000_000
    first = cycle.on_state(x, t_ns, 0.0, t_ns)
    assert isinstance(first, Planned)
    warm = cycle.planner.warm_start
    cycle.swap_planner(Planner(config, new), new.terrains)
    np.testing.assert_array_equal(cycle.planner.warm_start, warm)  # the warm start carries over
    names = list(reversed(new.terrains))  # weights by name, the learned ground on top
    assert cycle.on_weights([0.9, 0.04, 0.03, 0.03], 0.05, names=names)
    assert cycle.weights[-1] == pytest.approx(0.9)
    planned = cycle.on_state(x, t_ns + 100_000_000, 0.1, t_ns + 100_000_000)
    assert isinstance(planned, Planned) and np.all(np.isfinite(planned.result.controls))
    np.testing.assert_allclose(planned.result.weights, cycle.weights)
    # the old grounds' weights by their names are refused now: the model has four
    assert not cycle.on_weights([0.5, 0.3, 0.2], 0.2, names=list(model.terrains))


def test_a_collection_unknown_ground_started_is_dropped_when_the_ground_is_known_again() -> None:
    """A transient (a start from rest in the running stack) held `unknown` for 3 s on a trained ground: what it
    collected is no new ground, and learning starts over when new ground comes. A requested collection is kept."""
    from gpmppi.terrain.learning import GroundLearning, LearnConfig

    learning = GroundLearning(_model(), LearnConfig(steps=50, unknown_threshold=0.5, unknown_hold_s=3.0))
    assert learning.on_unknown(0.9, 0.0) is None and "learning ground 'new-1'" in learning.on_unknown(0.9, 3.0)
    assert learning.on_unknown(0.1, 4.0) is None and learning.on_unknown(0.9, 5.0) is None  # not known for long
    assert learning.on_unknown(0.1, 6.0) is None and learning.phase == "collecting"
    dropped = learning.on_unknown(0.1, 9.0)
    assert learning.phase == "idle" and dropped is not None and "learning 'new-1' dropped (0 steps" in dropped
    assert learning.on_unknown(0.9, 20.0) is None and "'new-1'" in learning.on_unknown(0.9, 23.0)  # new ground
    requested = GroundLearning(_model(), LearnConfig(steps=50, unknown_hold_s=3.0))
    requested.start("dune")
    assert requested.on_unknown(0.1, 0.0) is None and requested.on_unknown(0.1, 10.0) is None
    assert requested.phase == "collecting" and requested.name == "dune"


def test_learning_starts_on_request_or_after_unknown_ground_and_hands_out_one_fit() -> None:
    from gpmppi.terrain.learning import GroundLearning, LearnConfig, TeeEstimator

    model = _model()
    learning = GroundLearning(model, LearnConfig(steps=50, unknown_threshold=0.5, unknown_hold_s=3.0))
    assert learning.on_unknown(0.9, 10.0) is None and learning.on_unknown(0.2, 12.0) is None  # not for long
    assert learning.on_unknown(0.9, 13.0) is None and learning.phase == "idle"
    assert learning.on_unknown(0.8, 16.0) == "ground unknown for 3.0 s: learning ground 'new-1': collecting 50 steps"
    assert "already learning 'new-1'" in learning.start("mud")
    tee = TeeEstimator(make_estimator(model, EstimatorConfig()), learning)
    for row in drive(model, 49, seed=3):
        tee.observe(*row)  # the estimator's steps are the learner's
    assert len(learning.samples) == 49 and learning.take_job() is None
    tee.observe(*drive(model, 1, seed=4)[0])
    job = learning.take_job()
    assert job is not None and job.name == "new-1" and len(job.x) == 50 and learning.phase == "fitting"
    assert learning.take_job() is None  # one fit at a time
    new, _ = learn_ground(model, job.samples(), job.name, settings=SETTINGS.__class__(min_samples=50, max_points=40))
    learning.finished(new)
    assert learning.phase == "idle" and learning.start("") == "learning ground 'new-2': collecting 50 steps"
    assert learning.cancel() == "learning 'new-2' cancelled" and learning.phase == "idle"
