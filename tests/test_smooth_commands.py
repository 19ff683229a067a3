"""Smooth commands: the update's temperature chosen for an effective sample size (checked against scipy's softmax),
the Savitzky-Golay matrix (against scipy's filter), coloured sampling (the kernel's noise against a numpy AR(1)
reference, deterministic per seed), the default, the paper's form one setting away, and bad settings."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from cached_models import synthetic_model
from pydantic import ValidationError
from scipy.signal import savgol_filter
from scipy.special import softmax

from gpmppi.models.kinematic_unicycle import kinematic_step
from gpmppi.mppi import backends
from gpmppi.mppi.planner import Planner, PlannerConfig, savgol_matrix
from gpmppi.mppi.rng import noise_memory, sampled_noise, standard_noise
from gpmppi.mppi.temperature import temperature_for_effective_samples
from gpmppi.scenarios import circle_lane

W = np.array([0.5, 0.3, 0.2])


def _kish(costs: np.ndarray, temperature: float) -> float:
    w = softmax(-costs / temperature)
    return float(1.0 / np.sum(w * w))


@pytest.mark.parametrize("target", [1.5, 20.0, 200.0, 900.0])
def test_temperature_gives_the_target_effective_samples(target: float) -> None:
    costs = np.random.default_rng(4).gamma(2.0, 50.0, 1024) + 1e3
    t = temperature_for_effective_samples(costs, target, 1.0)
    assert _kish(costs, t) == pytest.approx(target, rel=1e-4)
    # scale-free: costs times 1000 need a temperature 1000 times higher, not a different sample size
    assert temperature_for_effective_samples(costs * 1e3, target, 1.0) == pytest.approx(1e3 * t, rel=1e-4)


def test_temperature_at_the_edges() -> None:
    costs = np.array([1.0, 2.0, np.inf, 4.0, np.inf])
    # only three costs are finite: a target above that is clipped to three (every finite cost weighs the same)
    t = temperature_for_effective_samples(costs, 10.0, 1.0)
    assert _kish(costs[np.isfinite(costs)], t) == pytest.approx(3.0, rel=1e-4)
    assert temperature_for_effective_samples(np.full(8, 5.0), 4.0, 0.7) == 0.7  # equal costs: temperature is moot
    assert temperature_for_effective_samples(np.full(8, np.inf), 4.0, 0.7) == 0.7  # none finite
    # costs that differ only by rounding (1e-300 apart: spread * 1e-9 underflows) are equal costs, not an error
    assert temperature_for_effective_samples(np.array([0.0, 1e-300, 2e-300]), 2.0, 0.7) == 0.7


def test_savgol_matrix_is_scipys_filter() -> None:
    u = np.random.default_rng(1).normal(size=(40, 2))
    np.testing.assert_allclose(savgol_matrix(40, 9, 2) @ u, savgol_filter(u, 9, 2, axis=0, mode="nearest"),
                               rtol=0, atol=1e-12)


def _rollout_noise(memory: float, seed: int = 7, iteration: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """The kernel's unit noise eps / noise_std of one call with limits too wide to clip, and its numpy reference."""
    p = Planner(PlannerConfig(dynamics="unicycle", backend="cpu", samples=2048, horizon=30, seed=seed,
                              v_limits=(-1e6, 1e6), omega_limits=(-1e6, 1e6)), synthetic_model())
    sc = circle_lane()
    bundle = p.terrain.set_weights(np.full(3, 1 / 3))
    from gpmppi.mppi.bundles import TaskBundle

    task = TaskBundle.for_lane(p.kind(sc.task).lane_lookup(sc.task), 1.0, np.ones(31), 1.0)
    std = np.array([0.5, 0.7])
    sampling = dataclasses.replace(p._sampling(sc.start, np.zeros((30, 2)), std), iteration=iteration,
                                   noise_memory=memory)
    eps, _, _ = backends.rollouts("cpu", bundle, task, sampling, p.kind(sc.task).cost, 2048, 0)
    return eps / std, sampled_noise(seed, iteration, 2048, 30, memory)


def test_coloured_noise_is_the_numpy_ar1_reference() -> None:
    d, ref = _rollout_noise(noise_memory(0.5, 0.1))
    np.testing.assert_allclose(d, ref, rtol=2e-6, atol=2e-6)  # eps is stored as float32
    a = noise_memory(0.5, 0.1)
    assert a == pytest.approx(np.exp(-0.2))
    # stationary: every step N(0, 1), lag-1 correlation = memory (the white noise's is 0)
    assert np.std(d[:, 10:]) == pytest.approx(1.0, abs=0.02)
    lag1 = np.mean(d[:, 1:] * d[:, :-1])
    assert lag1 == pytest.approx(a, abs=0.04)  # 3 standard errors of 2048 correlated sequences
    white, white_ref = _rollout_noise(0.0)
    np.testing.assert_allclose(white, standard_noise(7, 3, 2048, 30), rtol=2e-6, atol=2e-6)
    assert abs(np.mean(white[:, 1:] * white[:, :-1])) < 0.03
    np.testing.assert_array_equal(white_ref, standard_noise(7, 3, 2048, 30))


def _drive(cfg: PlannerConfig, steps: int = 25) -> tuple[np.ndarray, list]:
    sc = circle_lane()
    p = Planner(cfg, synthetic_model())
    x = sc.start.copy()
    results = []
    for _ in range(steps):
        r = p.plan(x, sc.task, W)
        results.append(r)
        x = kinematic_step(x, r.control, 0.1)
    return np.array([r.control for r in results]), results


def test_coloured_sampling_is_deterministic_per_seed() -> None:
    cfg = PlannerConfig(dynamics="gp", backend="cpu", samples=128, sampling="coloured", seed=11)
    a, _ = _drive(cfg, 4)
    b, _ = _drive(cfg, 4)
    np.testing.assert_array_equal(a, b)
    c, _ = _drive(cfg.model_copy(update={"seed": 12}), 4)
    assert not np.array_equal(a, c)
    white, _ = _drive(cfg.model_copy(update={"sampling": "white"}), 4)
    assert not np.array_equal(a, white)


def test_the_default_is_smooth_and_the_paper_form_is_one_setting_away() -> None:
    default = PlannerConfig()
    assert default.update == "smooth" and default.savgol_window == 9
    paper = PlannerConfig(update="paper")
    assert paper.savgol_window == 0 and paper.noise_memory == 0.0 and paper.temperature == 1.0
    base = {"dynamics": "unicycle", "backend": "cpu", "samples": 256, "sample_output": 256, "seed": 2}
    smooth_u, smooth = _drive(PlannerConfig(**base))
    paper_u, papers = _drive(PlannerConfig(**base, update="paper"))
    for r in papers:  # the paper's update: the fixed temperature's softmax over every rollout
        assert r.temperature == 1.0
        assert r.effective_samples == pytest.approx(_kish(np.asarray(r.sample_costs), 1.0), rel=1e-9)
    for r in smooth:  # the smooth update: the temperature that spreads it over 5 % of the samples
        assert r.effective_samples == pytest.approx(0.05 * 256, rel=1e-3)
        assert _kish(np.asarray(r.sample_costs), r.temperature) == pytest.approx(0.05 * 256, rel=1e-3)
    # the commands it sends change far less from one cycle to the next
    rate = lambda u: np.mean(np.abs(np.diff(u[5:], axis=0)), axis=0) / 0.1  # noqa: E731
    smooth_rate, paper_rate = rate(smooth_u), rate(paper_u)  # [m/s^2, rad/s^2]
    assert smooth_rate[0] < 0.5 * paper_rate[0] and smooth_rate[1] < 0.2 * paper_rate[1], (smooth_rate, paper_rate)


@pytest.mark.parametrize(("setting", "value"), [
    ("sampling", "pink"), ("update", "smoothest"), ("noise_correlation_time", 0.0), ("noise_correlation_time", -0.5),
    ("smoothing_window", 8), ("smoothing_window", 1), ("smoothing_window", 61), ("effective_sample_fraction", 0.0),
    ("effective_sample_fraction", 1.5),
])
def test_bad_smoothing_settings_are_refused_by_name(setting: str, value: object) -> None:
    with pytest.raises(ValidationError, match=setting):
        PlannerConfig(**{setting: value})
