"""The novelty test's free-run channel (gpmppi/terrain/free_run.py) sees a loss of grip that the one-step test cannot:
on synthetic responses (a ground that follows a trained one's response stays known; one that lags every trained
one's is flagged; a skipped step starts the runs over; the calibration's level is the logs' quantile; the profile
record's versions), and in a short drive of the physics plant through the terrain filter: the planner's commands
through a square lane's corner, on a trained ground and on glare ice, which only this channel flags."""

from __future__ import annotations

import numpy as np
import pytest

from gpmppi.profile.novelty_calibration import FreeRunCalibration, NoveltyCalibration
from gpmppi.profile.response import TerrainResponse
from gpmppi.terrain.free_run import DEFAULT_FREE_RUN, FreeRunTest, calibrate_free_run, profile_free_run

CAL = FreeRunCalibration(horizon_steps=5, window_steps=10, spread=(0.01, 0.01), enter=5.0, width=0.6)


def _response(gains: list[float], rate: float = 0.4) -> TerrainResponse:
    """Grounds whose steady (v, omega) is gain x the command (on a grid to 2 m/s and +-3 rad/s), one rate for all."""
    v_ref, omega_ref = np.linspace(0.0, 2.0, 5), np.linspace(-3.0, 3.0, 7)
    grid = np.stack(np.meshgrid(v_ref, omega_ref, indexing="ij"), axis=-1)
    steady = np.stack([g * grid for g in gains])
    return TerrainResponse(v_ref, omega_ref, tuple(f"g{i}" for i in range(len(gains))), steady,
                           np.full((len(gains), 2), rate))


def _drive(test: FreeRunTest, gain: float, rate: float, commands: np.ndarray, rng: np.random.Generator,
           noise: float = 0.008) -> list[float]:
    """Drive a ground with steady gain `gain` and approach `rate` under `commands`, measured with noise; P each step."""
    true = np.zeros(2)
    measured = true.copy()
    p = []
    for u in commands:
        true = true + rate * (gain * u - true)
        nxt = true + rng.normal(0.0, noise, 2)
        p.append(test.observe(measured, u, nxt))
        measured = nxt
    return p


def _commands(n: int, rng: np.random.Generator) -> np.ndarray:
    """Steps of held commands, changed every 1-2 s (as a driver does), within the grid."""
    out, u = [], np.array([1.0, 0.0])
    for k in range(n):
        if k % 15 == 0:
            u = np.array([rng.uniform(0.3, 1.8), rng.uniform(-2.0, 2.0)])
        out.append(u)
    return np.array(out)


def test_a_ground_that_follows_a_trained_response_stays_known_and_one_that_lags_them_all_is_flagged() -> None:
    rng = np.random.default_rng(0)
    test = FreeRunTest(_response([1.0, 0.8, 0.9]), CAL)
    p = _drive(test, gain=0.8, rate=0.4, commands=_commands(400, rng), rng=rng)
    assert max(p[:13]) == 0.0  # no whole window yet
    assert max(p) < 0.5 and test.best == 1
    # grip lost: the ground reaches only half the commanded speed and turn rate, and slowly (a slide); each step's
    # one-step error is small (the rate), the free run's error piles up over the horizon
    test.reset()
    slid = _drive(test, gain=0.5, rate=0.15, commands=_commands(200, rng), rng=rng)
    assert np.mean(np.array(slid[30:]) > 0.5) > 0.5


def test_a_skipped_step_or_a_command_off_the_grid_starts_the_free_runs_over() -> None:
    test = FreeRunTest(_response([1.0, 0.8]), CAL)
    u = np.array([1.0, 0.5])
    v = np.zeros(2)
    for _ in range(4):
        v1 = v + 0.4 * (u - v)
        test.observe(v, u, v1)
        v = v1
    assert test._active == 4
    test.observe(v + 0.3, u, v)  # does not start where the last step ended: a skipped transition
    assert test._active == 1
    test.observe(v, np.array([2.5, 0.0]), v)  # off the grid: no run, and none kept
    assert test._active == 0
    with pytest.raises(ValueError, match="whole window"):
        calibrate_free_run([(np.zeros((5, 2, 2)), 0)], window_steps=10)


def test_calibration_puts_the_enter_level_at_the_logs_quantile() -> None:
    rng = np.random.default_rng(1)
    bias = np.array([[0.0, 0.0], [0.05, 0.0], [0.0, 0.08]])
    runs = [(np.roll(bias[None] + rng.normal(0.0, 0.02, (800, 3, 2)), g, axis=1), g) for g in range(3)]
    cal = calibrate_free_run(runs, horizon_steps=5, window_steps=10, false_rate=0.01, source="synthetic")
    assert np.allclose(cal.spread, 0.02 / np.sqrt(10), rtol=0.15)
    from gpmppi.terrain.novelty import window_statistics

    fresh = bias[None] + rng.normal(0.0, 0.02, (3000, 3, 2))
    z = np.min(np.linalg.norm(window_statistics(fresh, 10) / np.array(cal.spread), axis=2), axis=1)
    assert 0.002 < np.mean(z > cal.enter) < 0.03  # ~1 % by construction


def test_the_profile_record_is_versioned_and_one_made_before_takes_the_stated_default(tmp_path) -> None:  # noqa: ANN001
    from cached_models import shipped_model

    from gpmppi.gp.model_file import GPModel
    from gpmppi.terrain.estimator import make_estimator
    from gpmppi.terrain.settings import EstimatorConfig

    v1 = {"window_steps": 20, "spread": [0.004, 0.012], "enter": 3.5, "width": 0.45, "source": "before"}
    old = NoveltyCalibration.from_metadata(v1)  # a record written before the free-run channel (no version key)
    assert old.free_run is None and "version" not in old.to_metadata()

    class Profile:
        novelty = old

    assert profile_free_run(Profile()) is DEFAULT_FREE_RUN and "default" in DEFAULT_FREE_RUN.source
    new = NoveltyCalibration(20, (0.004, 0.012), 3.5, 0.45, "logs",
                             FreeRunCalibration(10, 20, (0.03, 0.02), 6.0, 0.8, "logs"))
    meta = new.to_metadata()
    assert meta["version"] == 2 and NoveltyCalibration.from_metadata(meta) == new
    with pytest.raises(ValueError, match="version 3"):
        NoveltyCalibration.from_metadata({**meta, "version": 3})
    with pytest.raises(ValueError, match="horizon_steps"):
        FreeRunCalibration(0, 20, (0.03, 0.02), 6.0, 0.8)

    model = shipped_model()
    assert make_estimator(model, EstimatorConfig()).free_run.calibration is DEFAULT_FREE_RUN  # type: ignore[union-attr]
    model.novelty = new
    model.save(tmp_path / "p.npz")
    back = GPModel.load(tmp_path / "p.npz")
    assert back.novelty == new
    assert make_estimator(back, EstimatorConfig()).free_run.calibration == new.free_run  # type: ignore[union-attr]
    assert make_estimator(back, EstimatorConfig(novelty_free_run=False)).free_run is None  # type: ignore[union-attr]


# GP-MPPI's commands (v_ref [m/s], omega_ref [rad/s]) through a corner of the square lane, every 0.1 s, as it drove
# it on asphalt (`gpmppi evaluate tracking -m gp -t asphalt`, seed 0, 19.6-23.2 s)
CORNER = np.array([
    [1.11, 0.06], [1.05, 0.03], [1.07, 0.04], [1.16, -0.06], [1.14, -0.06], [1.24, -0.07], [1.28, -0.04],
    [1.25, 0.15], [1.34, 0.09], [1.34, 0.26], [1.36, 0.6], [1.26, 0.99], [1.28, 1.31], [1.22, 1.59], [1.14, 1.85],
    [1.2, 1.98], [1.2, 2.07], [1.27, 2.18], [1.27, 2.08], [1.31, 1.75], [1.49, 1.43], [1.55, 1.07], [1.54, 0.67],
    [1.52, 0.34], [1.47, 0.05], [1.54, -0.12], [1.62, -0.41], [1.62, -0.57], [1.6, -0.5], [1.62, -0.45],
    [1.46, -0.34], [1.5, -0.21], [1.59, -0.23], [1.5, -0.01], [1.5, 0.13], [1.45, 0.18]])
SWITCH_S = 8.0  # the ground changes on the straight, 1 s before the corner's steering
DT = 0.1


def lane_commands(after_steps: int = 30, corners: int = 1) -> np.ndarray:
    """A start, a straight with the small steering corrections a lane controller makes, then `corners` times the
    corner and a straight of `after_steps`."""
    t = np.arange(int(8.0 / DT)) * DT
    straight = np.column_stack([np.minimum(1.3, 0.3 + 0.5 * t), 0.08 * np.sin(1.3 * t)])
    after = np.column_stack([np.full(after_steps, 1.5), 0.05 * np.sin(1.3 * np.arange(after_steps) * DT)])
    return np.vstack([straight] + [CORNER, after] * corners)


def _p_unknown(ground: str, free_run: bool, channels: list[str] | None = None, commands: np.ndarray | None = None,
               back_at: int | None = None, grip_demand: float = 1.2, active: list[bool] | None = None) -> np.ndarray:
    from cached_models import shipped_model

    from gpmppi.plant.physics import PhysicsPlant
    from gpmppi.plant.terrains import load_terrains
    from gpmppi.terrain.estimator import make_estimator
    from gpmppi.terrain.settings import EstimatorConfig

    plant = PhysicsPlant(load_terrains("tests/data/new_grounds.yaml"), "asphalt", seed=0, noise=True)
    plant.reset(np.zeros(5))
    est = make_estimator(shipped_model(), EstimatorConfig(novelty_free_run=free_run,
                                                               novelty_grip_demand=grip_demand))
    x = plant.measure()
    p = []
    for k, u in enumerate(lane_commands() if commands is None else commands):
        if k == round(SWITCH_S / DT):
            plant.set_terrain(ground)
        if k == back_at:  # off the new ground, back on the one the drive started on
            plant.set_terrain("asphalt")
        plant.step(u, DT)
        x1 = plant.measure()
        est.observe(x, u, x1)
        estimate = est.estimate()
        p.append(estimate.unknown)
        if channels is not None:
            channels.append(estimate.unknown_channel)
        if active is not None:
            active.append(estimate.unknown_active)
        x = x1
    return np.array(p)


def test_glare_ice_in_a_corner_is_flagged_by_the_free_run_and_missed_by_the_one_step_test() -> None:
    channels: list[str] = []
    on_ice = _p_unknown("glare_ice", free_run=True, channels=channels)
    first = int(np.argmax(on_ice > 0.5))
    assert on_ice[first] > 0.5, f"glare ice never flagged (P at most {on_ice.max():.2f})"
    assert channels[first] == "free-run"  # what the terrain service's log line names
    assert first * DT - SWITCH_S <= 3.0, f"flagged {first * DT - SWITCH_S:.1f} s after the change"
    assert max(on_ice[: round(SWITCH_S / DT)]) < 0.5
    without = _p_unknown("glare_ice", free_run=False)
    assert without.max() < 0.5, f"the one-step test alone reached {without.max():.2f}: this drive tests nothing"
    for trained in ("asphalt", "tile"):  # the same drive on trained grounds, tile the nearest to glare ice
        assert _p_unknown(trained, free_run=True).max() < 0.5, trained


def test_the_free_run_alarm_holds_through_a_straight_and_falls_on_a_corner_driven_on_known_ground() -> None:
    """Synthetic: a slide in a corner raises the alarm; on the straight after it the ground follows a trained
    response (as glare ice does there), which carries no evidence of grip, and the alarm holds; a corner on a ground
    that follows a trained response clears it. Without the hold (`informative_demand` 0) it falls on the straight."""
    rng = np.random.default_rng(3)
    straight = np.tile([1.0, 0.05], (60, 1))  # 0.05 m/s^2 sideways: steering corrections
    corner = np.tile([1.0, 2.0], (25, 1))  # 2 m/s^2 sideways
    held, plain = FreeRunTest(_response([1.0, 0.8]), CAL), FreeRunTest(_response([1.0, 0.8]), CAL, 0.0)
    for test in (held, plain):
        assert max(_drive(test, 1.0, 0.4, straight[:30], rng)) < 0.5  # a start and a straight on known ground
        test._at = None  # each `_drive` starts from rest: the runs start over
        slide = _drive(test, 0.5, 0.15, corner, rng)  # grip lost: half the commanded turn rate, slowly
        assert max(slide) > 0.5
        test._at = None
    on_straight = _drive(held, 1.0, 0.4, straight, rng)
    assert min(on_straight) > 0.5 and held.window_statistic < 1.0  # the plain window is known ground's; held
    assert _drive(plain, 1.0, 0.4, straight, rng)[-1] < 0.01  # without the hold: "known again" on the straight
    held._at = None
    assert _drive(held, 1.0, 0.4, corner, rng)[-1] < 0.01  # a corner on known ground: known again


def test_an_alarm_of_runs_that_asked_for_no_grip_is_not_held() -> None:
    """Synthetic: on a straight the robot lags every trained response (as at the stack's start, where a stalled
    planner's zero command braked the robot harder than the response's first order): the alarm rises, but none of the
    window's runs asked for grip, so it is not held and falls once the straight is followed again, as without the
    hold (held, it would stay up on any drive that never asks for grip: a circle's whole run was 'unknown' so)."""
    rng = np.random.default_rng(4)
    straight = np.tile([1.0, 0.05], (60, 1))
    held, plain = FreeRunTest(_response([1.0, 0.8]), CAL), FreeRunTest(_response([1.0, 0.8]), CAL, 0.0)
    for test in (held, plain):
        assert max(_drive(test, 1.0, 0.4, straight[:30], rng)) < 0.5
        test._at = None
        lag = _drive(test, 0.5, 0.15, straight[:25], rng)  # lags on the straight: no grip asked
        assert max(lag) > 0.5
        test._at = None
        assert _drive(test, 1.0, 0.4, straight, rng)[-1] < 0.01  # falls on the straight, held or not


def test_glare_ice_flagged_in_a_corner_stays_unknown_on_the_straight_and_a_trained_corner_clears_it() -> None:
    """The physics plant through the filter: glare ice from the change on, a corner, 6 s of straight; then asphalt,
    and the next corner. The alarm raised in the first corner holds through the straight (without the hold it falls
    there), and falls after the corner on asphalt; asphalt throughout (a start, straights, two corners) raises none."""
    commands = lane_commands(after_steps=60, corners=2)
    second = round(SWITCH_S / DT) + len(CORNER) + 60  # where the second corner starts
    active: list[bool] = []
    held = _p_unknown("glare_ice", True, commands=commands, back_at=second - 20, active=active)
    plain = _p_unknown("glare_ice", True, commands=commands, back_at=second - 20, grip_demand=0.0)
    first = int(np.argmax(held > 0.5))
    assert held[first] > 0.5 and first * DT - SWITCH_S <= 3.0
    straight = slice(first + 25, second)  # the straight after the corner, until the next corner
    assert held[straight].min() > 0.5 and all(active[straight]), held[straight].round(2)
    assert plain[straight].min() < 0.2, "without the hold the alarm should fall on the straight: this tests nothing"
    assert held[-1] < 0.2 and not active[-1]  # known again after the corner on asphalt
    assert _p_unknown("asphalt", True, commands=commands).max() < 0.5
