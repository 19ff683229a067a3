"""The absolute test of fit (gpmppi/terrain/novelty.py) on synthetic residuals: known ground stays known, a shifted
one is flagged within its window, the best ground decides, the decision has hysteresis, and a calibration from
known-ground steps puts P = 0.5 at the quantile it says."""

from __future__ import annotations

import numpy as np
import pytest

from gpmppi.profile.novelty_calibration import NoveltyCalibration
from gpmppi.terrain.novelty import (
    DEFAULT_CALIBRATION,
    ENTER_SPREADS,
    SETTLE_STEPS,
    NoveltyTest,
    UnknownLatch,
    calibrate,
    profile_novelty,
)

CAL = NoveltyCalibration(window_steps=10, spread=(0.006, 0.012), enter=3.0, width=0.4)
STEP_STD = np.array([0.015, 0.03])  # per-step residual scatter [m/s, rad/s]: windowed mean ~ STEP_STD / sqrt(10)


def _residuals(rng: np.random.Generator, n: int, bias: np.ndarray) -> np.ndarray:
    """(n, 3, 2) residuals under 3 grounds: ground g has mean bias[g] and the per-step scatter."""
    return bias[None, :, :] + rng.normal(size=(n, 3, 2)) * STEP_STD


def test_known_ground_stays_known_and_a_shifted_ground_is_flagged_within_its_window() -> None:
    rng = np.random.default_rng(0)
    test = NoveltyTest(3, CAL)
    known = np.array([[0.0, 0.0], [0.03, 0.01], [-0.03, 0.02]])  # ground 0 explains the steps
    p = [test.observe(r) for r in _residuals(rng, 400, known)]
    assert max(p[:9]) == 0.0  # no whole window yet: not assessed
    assert np.mean(np.array(p) > 0.5) < 0.01 and test.best == 0
    # a new ground: every trained ground's prediction is off (the nearest by 0.02 m/s and 0.07 rad/s)
    shifted = known + np.array([-0.05, 0.06])
    after = [test.observe(r) for r in _residuals(rng, 30, shifted)]
    first = int(np.argmax(np.array(after) > 0.5))
    assert after[first] > 0.5 and first < 10  # within one window of the change
    assert min(after[10:]) > 0.9


def test_it_is_the_best_ground_that_decides() -> None:
    """A ground that only one trained ground explains is known, however badly the others fit."""
    rng = np.random.default_rng(1)
    test = NoveltyTest(3, CAL)
    bias = np.array([[0.2, 0.3], [0.0, 0.0], [-0.2, 0.1]])
    p = [test.observe(r) for r in _residuals(rng, 200, bias)]
    assert np.mean(np.array(p[10:]) > 0.5) < 0.02 and test.best == 1


def test_non_finite_residuals_are_not_scored() -> None:
    test = NoveltyTest(2, CAL)
    for _ in range(10):
        test.observe(np.zeros((2, 2)))
    before = test.statistic
    assert test.observe(np.full((2, 2), np.nan)) == test.probability and test.statistic == before


def test_the_decision_has_hysteresis() -> None:
    latch = UnknownLatch(enter_p=0.5, exit_p=0.2, exit_steps=3)
    assert not latch.update(0.45)
    assert latch.update(0.6)
    assert latch.update(0.3)  # between the levels: stays
    assert latch.update(0.1) and latch.update(0.1)  # two steps below: stays
    assert latch.update(0.6) and latch.update(0.1) and latch.update(0.1)  # back above resets the count
    assert not latch.update(0.1)  # three in a row below exit_p: cleared


def test_calibration_puts_the_enter_level_at_the_quantile_of_known_ground() -> None:
    rng = np.random.default_rng(2)
    bias = np.array([[0.0, 0.0], [0.05, 0.0], [0.0, 0.08]])
    runs = [(np.roll(_residuals(rng, 500, bias), g, axis=1), g) for g in range(3)]
    assert calibrate(runs, window_steps=10).enter == ENTER_SPREADS  # the stated level, by default
    cal = calibrate(runs, window_steps=10, enter=None, false_rate=0.01, source="synthetic")
    assert np.allclose(cal.spread, STEP_STD / np.sqrt(10), rtol=0.15)
    test = NoveltyTest(3, cal)
    fresh = [test.observe(r) for r in _residuals(rng, 2000, bias)]
    assert 0.002 < np.mean(np.array(fresh[9:]) > 0.5) < 0.03  # ~1 % by construction
    with pytest.raises(ValueError, match="whole window"):
        calibrate([(np.zeros((5, 3, 2)), 0)], window_steps=10)


def test_bad_calibrations_are_refused_and_a_profile_without_one_takes_the_stated_default() -> None:
    with pytest.raises(ValueError, match="spread"):
        NoveltyCalibration(10, (0.0, 0.01), 3.0, 0.4)
    with pytest.raises(ValueError, match="window_steps"):
        NoveltyCalibration(0, (0.01, 0.01), 3.0, 0.4)

    class Profile:  # a profile made before the test: no `novelty`
        pass

    assert profile_novelty(Profile()) is DEFAULT_CALIBRATION
    assert "default" in DEFAULT_CALIBRATION.source


def test_a_profile_keeps_its_novelty_calibration_and_one_without_loads_with_the_default(tmp_path) -> None:  # noqa: ANN001
    from cached_models import shipped_model

    from gpmppi.gp.model_file import GPModel
    from gpmppi.terrain.estimator import make_estimator
    from gpmppi.terrain.settings import EstimatorConfig

    shipped = shipped_model()  # made before the test: no calibration of its own
    assert shipped.novelty is None
    est = make_estimator(shipped, EstimatorConfig())
    assert est.novelty.calibration is DEFAULT_CALIBRATION  # type: ignore[union-attr]
    shipped.novelty = NoveltyCalibration(20, (0.004, 0.01), 4.0, 0.5, "fitted on the logs of a test")
    shipped.save(tmp_path / "p.npz")
    back = GPModel.load(tmp_path / "p.npz")
    assert back.novelty == shipped.novelty
    assert make_estimator(back, EstimatorConfig()).novelty.calibration == shipped.novelty  # type: ignore[union-attr]
    assert make_estimator(back, EstimatorConfig(novelty=False)).novelty is None  # type: ignore[union-attr]


def test_transients_and_the_steps_after_them_are_not_scored() -> None:
    """A step from rest or with the v command more than `max_speed_gap` from the speed, in either direction, is a
    transient; it and the `SETTLE_STEPS` after the last one leave the window as it was."""
    test = NoveltyTest(3, CAL, max_speed_gap=0.3)
    assert test.transient(0.5, 0.0, 0.0) and test.transient(0.0, 0.8, 0.2) and test.transient(1.3, 0.9, 0.0)
    assert not test.transient(1.0, 0.9, 0.0) and not test.transient(0.0, 0.0, 0.5)  # turning on the spot: moving
    rng = np.random.default_rng(3)
    known = _residuals(rng, 30, np.zeros((3, 2)))
    for r in known[:20]:
        test.observe(r)
    before = test.statistic
    huge = np.full((3, 2), 0.5)
    assert test.observe(huge, transient=True) < 0.5 and test.statistic == before
    for _ in range(SETTLE_STEPS):
        test.observe(huge)  # the settling steps after it: not scored either
    assert test.statistic == before and test.probability < 0.5
    test.observe(huge)  # then scoring resumes
    assert test.statistic > before


@pytest.mark.parametrize(("new_grounds", "robot_file"), [
    ("tests/data/new_grounds.yaml", None),
    ("tests/data/new_grounds_light.yaml", "tests/data/light_fast.yaml"),
    ("tests/data/new_grounds_heavy.yaml", "docs/robots/heavy_wide.yaml"),
])
def test_the_new_ground_sets_are_their_robots_with_grounds_added(new_grounds: str, robot_file: str | None) -> None:
    """docs/new_ground.md measures detection on three robots with these files: each must be its robot, unchanged, and
    every ground of the robot's own set, unchanged, plus the new ones (a drifted copy would measure another robot)."""
    from gpmppi.plant.terrains import load_terrains

    new, base = load_terrains(new_grounds), load_terrains(robot_file)
    assert new.robot == base.robot
    assert {k: new.terrains[k] for k in base.terrains} == base.terrains and len(new.terrains) > len(base.terrains)
