"""The lateral slip model: its fit from poses, the physics plant's slide it captures, and its place in the planner."""

from __future__ import annotations

import numpy as np
import pytest
from cached_models import synthetic_model

from gpmppi.gp.model_file import GPModel, ModelFileError
from gpmppi.gp.train import fit_lateral_from_series
from gpmppi.models.dynamic_unicycle import nominal_step
from gpmppi.models.lateral_slip import body_lateral_velocity, fit_lateral_slip, lateral_features, lateral_velocity
from gpmppi.mppi.dynamics import DYN_GP, advance, velocity_coefficients
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.plant.physics import PhysicsPlant
from gpmppi.plant.terrains import load_terrains

THETA = np.array([0.2155, 0.3266, 0.0514, 1.0670, 0.1660, 1.0790])


def _drive(a: float, b: float, n: int = 3000, dt: float = 0.1) -> dict[str, np.ndarray]:
    """Poses of a robot that slides sideways by exactly `lateral_velocity(a, b)` at each step's mean velocities."""
    k = np.arange(n)
    v = 1.0 + 0.6 * np.sin(0.011 * k)
    w = 1.8 * np.sin(0.023 * k)
    x, y, yaw = np.zeros(n), np.zeros(n), np.zeros(n)
    for i in range(n - 1):
        vm, wm = 0.5 * (v[i] + v[i + 1]), 0.5 * (w[i] + w[i + 1])
        vy = lateral_velocity(a, b, vm, wm)
        h = yaw[i] + 0.5 * wm * dt
        x[i + 1] = x[i] + (vm * np.cos(h) - vy * np.sin(h)) * dt
        y[i + 1] = y[i] + (vm * np.sin(h) + vy * np.cos(h)) * dt
        yaw[i + 1] = yaw[i] + wm * dt
    # logged yaw is wrapped; segments break the series (no step is formed across a break)
    return {"v": v, "w": w, "x": x, "y": y, "yaw": np.angle(np.exp(1j * yaw)), "seg": k // 700}


def test_fit_recovers_the_slide_from_wrapped_poses_across_segments() -> None:
    s = _drive(-0.04, -0.08)
    np.testing.assert_allclose(fit_lateral_from_series(s, 0.1), [-0.04, -0.08], atol=1e-9)
    i, _ = body_lateral_velocity(s["x"], s["y"], s["yaw"], 0.1, s["seg"])
    assert len(i) == len(s["x"]) - 1 - 4  # four segment breaks
    # a break between segments: a jump in the poses there must not enter the fit
    s["x"][700:] += 5.0
    np.testing.assert_allclose(fit_lateral_from_series(s, 0.1), [-0.04, -0.08], atol=1e-9)


def test_fit_is_zero_without_turns_at_speed_and_none_without_poses() -> None:
    n = 500
    assert np.all(fit_lateral_slip(np.full(n, 1.0), np.zeros(n), np.full(n, 0.3)) == 0.0)
    assert fit_lateral_from_series({"v": np.ones(5), "w": np.ones(5), "seg": np.zeros(5)}, 0.1) is None


def test_the_fit_captures_the_physics_plants_slide_on_tile() -> None:
    """Noisy logged poses of a random drive -> coefficients that predict the plant's true sideways velocity."""
    plant = PhysicsPlant(load_terrains(None), "tile", seed=3, noise=True)
    plant.reset(np.zeros(5))
    rng = np.random.default_rng(3)
    rows, true_vy = [], []
    cmd = np.zeros(2)
    for k in range(2400):
        if k % 15 == 0:
            cmd = np.array([rng.uniform(0.3, 1.8), rng.uniform(-1.6, 1.6)])
        rows.append(plant.measure())
        true_vy.append(plant.lateral_velocity)
        plant.step(cmd, 0.1)
    m = np.array(rows)
    series = {"v": m[:, 3], "w": m[:, 4], "x": m[:, 0], "y": m[:, 1], "yaw": m[:, 2], "seg": np.zeros(len(m))}
    a, b = fit_lateral_from_series(series, 0.1)
    assert a < 0.0 or b < 0.0  # turning left slides the robot right (outwards)
    true = np.array(true_vy)
    pred = lateral_features(m[:, 3], m[:, 4]) @ np.array([a, b])
    turning = np.abs(m[:, 3] * m[:, 4]) > 0.5
    # the model explains most of the slide where it matters (the planner had none: error = the slide itself)
    err, none = np.sqrt(np.mean((pred - true)[turning] ** 2)), np.sqrt(np.mean(true[turning] ** 2))
    assert err < 0.4 * none, (err, none)


def test_rollout_step_is_the_model_step_with_the_slide() -> None:
    rng = np.random.default_rng(7)
    lat = np.array([-0.05, -0.1])
    coef = velocity_coefficients(THETA, lat)
    for _ in range(20):
        x = rng.uniform([-5, -5, -np.pi, 0, -2], [5, 5, np.pi, 2, 2])
        u = rng.uniform([0, -2], [2, 2])
        mv, mw = rng.uniform(-0.1, 0.1, 2)
        ref = nominal_step(THETA, x, u, 0.1, mv, mw, *lat)
        got = np.array(advance(DYN_GP, 0.1, coef, np.ones(5), tuple(x), tuple(u), mv, mw))
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-6)  # rollouts take cos/sin in float32
        plain = nominal_step(THETA, x, u, 0.1, mv, mw)
        vm, wm = 0.5 * (x[3] + ref[3]), 0.5 * (x[4] + ref[4])
        h = x[2] + 0.5 * wm * 0.1
        side = np.array([-np.sin(h), np.cos(h)])  # the slide moves the pose sideways only, by v_y dt
        assert (ref[:2] - plain[:2]) @ side == pytest.approx(lateral_velocity(*lat, vm, wm) * 0.1, abs=1e-12)


def test_planner_blends_the_slide_by_the_terrain_weights() -> None:
    model = synthetic_model()
    lat = {t: np.array([-0.02 * (i + 1), -0.05 * i]) for i, t in enumerate(model.terrains)}
    model.lateral_slip = lat
    w = np.array([0.5, 0.3, 0.2])
    p = Planner(PlannerConfig(samples=16, horizon=8, backend="cpu"), model)
    p.prepare(w)
    blended = sum(w[i] * lat[t] for i, t in enumerate(model.terrains))
    np.testing.assert_allclose(p.terrain.set_weights(w).lateral, blended)
    # the planned states follow the model step with those coefficients
    x0 = np.array([0.0, 0.0, 0.3, 1.2, 0.8])
    states, _, _ = p._propagate(x0, np.tile([1.2, 1.0], (8, 1)), p.terrain.set_weights(w), np.zeros((5, 5)))
    plain = Planner(PlannerConfig(samples=16, horizon=8, backend="cpu"), synthetic_model())
    plain.prepare(w)
    states0, _, _ = plain._propagate(x0, np.tile([1.2, 1.0], (8, 1)), plain.terrain.set_weights(w),
                                      np.zeros((5, 5)))
    assert np.linalg.norm(states[-1, :2] - states0[-1, :2]) > 0.01
    np.testing.assert_allclose(states[:, 2:], states0[:, 2:], atol=1e-12)  # heading and velocities unchanged
    edd5 = Planner(PlannerConfig(samples=16, horizon=8, backend="cpu", dynamics="edd5"), model)
    edd5.prepare(w)
    assert np.all(edd5.terrain.set_weights(w).lateral == 0.0)  # the baselines are the paper's models


def test_model_file_keeps_the_slide_and_old_files_load_without_it(tmp_path) -> None:  # noqa: ANN001
    model = synthetic_model()
    model.lateral_slip = {t: np.array([-0.01 * (i + 1), 0.02]) for i, t in enumerate(model.terrains)}
    path = tmp_path / "m.npz"
    model.save(path)
    back = GPModel.load(path)
    np.testing.assert_array_equal(back.lateral_matrix(), model.lateral_matrix())
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    old = dict(arrays)
    del old["lateral_slip"]
    np.savez(tmp_path / "old.npz", **old)
    assert np.all(GPModel.load(tmp_path / "old.npz").lateral_matrix() == 0.0)
    bad = dict(arrays)
    bad["lateral_slip"] = np.zeros((len(model.terrains), 3))
    np.savez(tmp_path / "bad.npz", **bad)
    with pytest.raises(ModelFileError, match="lateral_slip"):
        GPModel.load(tmp_path / "bad.npz")
