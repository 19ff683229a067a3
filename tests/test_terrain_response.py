"""Each terrain's velocity response (gpmppi/profile/response.py) and the terrain filter's use of it: the map
interpolates like scipy's, the rate fit recovers a known rate, the shipped file is what `gpmppi evaluate
terrain-response` writes, held commands on the physics plant are identified with it (and were not without it),
a skipped transition re-anchors the response, and bad files or settings fail naming what is wrong."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cached_models import shipped_model
from scipy.interpolate import RegularGridInterpolator
from typer.testing import CliRunner

from gpmppi.plant.physics import PhysicsPlant
from gpmppi.plant.terrains import load_terrains
from gpmppi.profile.response import SHIPPED_RESPONSE, TerrainResponse, load_response
from gpmppi.terrain.calibration import fit_rate
from gpmppi.terrain.estimator import BayesTerrainEstimator, make_estimator
from gpmppi.terrain.settings import EstimatorConfig


def _random_response(seed: int = 0) -> TerrainResponse:
    rng = np.random.default_rng(seed)
    v_ref, omega_ref = np.array([0.0, 0.5, 1.2, 2.0]), np.array([-2.0, -0.3, 0.0, 0.8, 2.0])
    return TerrainResponse(v_ref, omega_ref, ("a", "b"), rng.normal(size=(2, 4, 5, 2)), np.array([[0.3, 0.2],
                                                                                                  [0.5, 1.0]]))


def test_steady_map_is_bilinear_like_scipy_and_clamped_to_the_grid() -> None:
    r = _random_response()
    rng = np.random.default_rng(1)
    for u in rng.uniform([0.0, -2.0], [2.0, 2.0], size=(50, 2)):
        expected = np.stack([RegularGridInterpolator((r.v_ref, r.omega_ref), r.steady[i])(u)[0] for i in range(2)])
        np.testing.assert_allclose(r.steady_at(u), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(r.steady_at(np.array([5.0, -9.0])), r.steady[:, -1, 0])  # clamped, not extrapolated
    assert r.covers(np.array([2.0, -2.0])) and r.covers(np.array([0.0, 0.3]))
    assert not r.covers(np.array([1.0, -2.01])) and not r.covers(np.array([2.1, 0.0]))
    p = np.array([[0.1, 0.2], [0.3, 0.4]])
    u = np.array([1.0, 0.5])
    np.testing.assert_allclose(r.step(p, u), p + r.rate * (r.steady_at(u) - p))


def test_rate_fit_recovers_the_rate_of_a_first_order_response() -> None:
    r = _random_response()
    one = TerrainResponse(r.v_ref, r.omega_ref, ("a",), r.steady[:1], r.rate[:1])
    rng = np.random.default_rng(2)
    commands = np.repeat(rng.uniform([0.0, -2.0], [2.0, 2.0], size=(40, 2)), 5, axis=0)
    states = np.zeros((len(commands) + 1, 5))
    for k, u in enumerate(commands):
        states[k + 1, 3:5] = one.step(states[k:k + 1, 3:5], u)[0]
    np.testing.assert_allclose(fit_rate(lambda c: one.steady_at(c)[0], states, commands), r.rate[0], rtol=1e-9)


def test_the_response_file_reads_bit_for_bit_as_pure_python_yaml_reads_it() -> None:
    """`load_response` parses with libyaml's scanner where PyYAML has it (7 ms instead of 52 ms of CPU a read, which
    every terrain estimator pays): every number as PyYAML's own pure-Python loader reads it, to the bit."""
    import yaml

    r = load_response()
    data = yaml.load(Path(SHIPPED_RESPONSE).read_text(), Loader=yaml.SafeLoader)  # the pure-Python loader
    assert r.terrains == tuple(data["terrains"])
    np.testing.assert_array_equal(r.v_ref, np.asarray(data["v_ref"], dtype=np.float64))
    np.testing.assert_array_equal(r.omega_ref, np.asarray(data["omega_ref"], dtype=np.float64))
    for i, entry in enumerate(data["terrains"].values()):
        np.testing.assert_array_equal(r.steady[i, ..., 0], np.asarray(entry["v"], dtype=np.float64))
        np.testing.assert_array_equal(r.steady[i, ..., 1], np.asarray(entry["omega"], dtype=np.float64))
        np.testing.assert_array_equal(r.rate[i], np.asarray(entry["rate"], dtype=np.float64))


def test_the_shipped_response_is_what_the_fit_command_writes(tmp_path: Path) -> None:
    from tools.cli import app

    out = tmp_path / "response.yaml"
    result = CliRunner().invoke(app, ["evaluate", "terrain-response", "-o", str(out)])
    assert result.exit_code == 0, result.output
    shipped, fitted = load_response(SHIPPED_RESPONSE), load_response(out)
    assert fitted.terrains == shipped.terrains == tuple(shipped_model().terrains)
    np.testing.assert_array_equal(fitted.steady, shipped.steady)
    np.testing.assert_array_equal(fitted.rate, shipped.rate)
    # what makes it useful: at a held turn the terrains settle apart (asphalt's skid moment resists turning, tile
    # turns easily, grass drags), by more than the sensor noise averaged over the settled window
    asphalt, grass, tile = shipped.select(["asphalt", "grass", "tile"]).steady_at(np.array([1.3, 0.8]))
    assert grass[1] + 0.03 < asphalt[1] < tile[1] - 0.03


def _held_drive(terrain: str, command: tuple[float, float], seconds: float, seed: int):
    """(state, command, next state) steps of the physics plant (sensor noise on) under one held command from rest."""
    plant = PhysicsPlant(load_terrains(), terrain, seed=seed)
    plant.reset(np.zeros(5))
    u = np.asarray(command, dtype=np.float64)
    x = plant.measure()
    rows = []
    for _ in range(int(round(seconds / 0.1))):
        plant.step(u, 0.1)
        x1 = plant.measure()
        rows.append((x, u, x1))
        x = x1
    return rows


@pytest.mark.parametrize("terrain", ["asphalt", "grass", "tile"])
def test_a_held_command_is_identified_by_its_response(terrain: str) -> None:
    model = shipped_model()
    rows = _held_drive(terrain, (1.3, 0.6), 12.0, seed=4)
    with_response = make_estimator(model)
    for row in rows:
        with_response.observe(*row)
    i = list(model.terrains).index(terrain)
    assert with_response.estimate().weights[i] > 0.9


def test_the_gp_alone_misreads_steady_asphalt() -> None:
    # why the response is there: at a held command the GP's one-step residuals point away from asphalt
    model = shipped_model()
    gp_only = make_estimator(model, EstimatorConfig(response="none"))
    for row in _held_drive("asphalt", (1.3, 0.6), 12.0, seed=4):
        gp_only.observe(*row)
    assert gp_only.estimate().weights[list(model.terrains).index("asphalt")] < 0.5


@pytest.mark.parametrize("terrain", ["asphalt", "tile"])
def test_anchored_to_the_steady_map_the_gp_alone_reads_a_held_command_right(terrain: str) -> None:
    # `gp_anchor` takes out of each terrain's GP mean its bias at that terrain's measured steady state: the GP evidence
    # alone (no response scored) then leads with the terrain driven on where, unanchored, it all but rules it out
    # (measured: asphalt 0.07 -> 0.66, tile 0.04 -> 0.58)
    model = shipped_model()
    i = list(model.terrains).index(terrain)
    rows = _held_drive(terrain, (1.3, 0.6), 12.0, seed=4)
    weights = {}
    for anchor in (False, True):
        est = make_estimator(model, EstimatorConfig(response="none", gp_anchor=anchor))
        for row in rows:
            est.observe(*row)
        weights[anchor] = est.estimate().weights
    assert weights[False][i] < 0.15, weights
    assert weights[True][i] > 0.5 and int(np.argmax(weights[True])) == i, weights


def test_the_anchor_leaves_the_novelty_test_its_unanchored_residuals() -> None:
    # the novelty test is calibrated on the GP's own residuals: with `gp_anchor` it must read the same residuals as
    # without it (the anchor's correction taken back out), not the correction twice over, which read a held command
    # on a trained ground as unknown ground (a 45 kg mulch launch replayed with the anchor: P(unknown) > 0.5 for 29 %
    # of the time, none without it)
    model = shipped_model()
    rows = _held_drive("asphalt", (1.3, 0.6), 6.0, seed=4)
    tests = {}
    for anchor in (False, True):
        est = make_estimator(model, EstimatorConfig(response="none", gp_anchor=anchor))
        assert isinstance(est, BayesTerrainEstimator) and est.novelty is not None
        for row in rows:
            est.observe(*row)
        tests[anchor] = est.novelty
        if anchor:
            assert np.max(np.abs(est._steady_bias(rows[-1][1]))) > 0.01  # the anchor corrects this command
    assert tests[True].ready
    np.testing.assert_allclose(tests[True]._sum, tests[False]._sum, atol=1e-12)
    assert tests[True].statistic == pytest.approx(tests[False].statistic, abs=1e-9)


def test_a_skipped_transition_re_anchors_the_response() -> None:
    model = shipped_model()
    est = make_estimator(model)
    assert isinstance(est, BayesTerrainEstimator)
    rows = _held_drive("tile", (1.0, 0.3), 2.0, seed=5)
    for row in rows[:5]:
        est.observe(*row)
    x, u, x1 = rows[10]  # rows 5-9 never observed: this step does not start where the last one ended
    est.observe(x, u, x1)
    response = model.require_calibration().response.select(list(model.terrains))  # what the estimator reads
    np.testing.assert_allclose(est._response_pred, response.step(np.tile(x[3:5], (3, 1)), u))


def test_bad_response_files_fail_naming_the_file_and_the_fix(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("version: 1\nv_ref: [0.0, 1.0]\n")
    with pytest.raises(ValueError, match=r"terrain response file .*bad.yaml.*gpmppi evaluate terrain-response"):
        load_response(bad)
    text = SHIPPED_RESPONSE.read_text()
    bad.write_text(text.replace("rate: [0.2867", "rate: [1.5", 1))
    with pytest.raises(ValueError, match=r"bad.yaml.*rate must lie in \(0, 1\]"):
        load_response(bad)
    only = tmp_path / "only_asphalt.yaml"
    r = load_response()
    only.write_text(r.select(["asphalt"]).to_yaml())
    with pytest.raises(ValueError, match=r"response_file .*only_asphalt.yaml: no response for terrain\(s\) "
                                         r"\['grass', 'tile'\].*gpmppi evaluate terrain-response"):
        make_estimator(shipped_model(), EstimatorConfig(response_file=str(only)))


def test_jittery_commands_leave_the_response_unscored() -> None:
    # under commands that jump every step (the paper's update) a first-order response's average is biased: the filter
    # scores the GP evidence alone, exactly as with response: none
    model = shipped_model()
    plant = PhysicsPlant(load_terrains(), "grass", seed=6)
    plant.reset(np.zeros(5))
    rng = np.random.default_rng(6)
    x = plant.measure()
    rows = []
    for _ in range(60):
        u = np.array([rng.uniform(0.8, 1.8), rng.uniform(-1.5, 1.5)])
        plant.step(u, 0.1)
        x1 = plant.measure()
        rows.append((x, u, x1))
        x = x1
    default, gp_only = make_estimator(model), make_estimator(model, EstimatorConfig(response="none"))
    for row in rows:
        default.observe(*row)
        gp_only.observe(*row)
    np.testing.assert_array_equal(default.estimate().weights, gp_only.estimate().weights)
    smooth = make_estimator(model)  # and held commands are scored: the weights differ
    plain = make_estimator(model, EstimatorConfig(response="none"))
    for row in _held_drive("grass", (1.3, 0.6), 5.0, seed=6):
        smooth.observe(*row)
        plain.observe(*row)
    assert not np.array_equal(smooth.estimate().weights, plain.estimate().weights)


def test_the_shipped_grid_covers_the_planners_commands() -> None:
    # off the grid the map is clamped; a pivot at the planner's yaw-rate limit must still be on it
    from gpmppi.mppi.planner import PlannerConfig

    cfg, r = PlannerConfig(), load_response()
    for v in cfg.v_limits:
        for w in cfg.omega_limits:
            assert r.covers(np.array([v, w])), (v, w)


def test_a_command_off_the_grid_adds_no_response_evidence(tmp_path: Path) -> None:
    # a map measured to +-1 rad/s, a turn held at 1.6 rad/s: the clamped map would be off by ~0.5 rad/s, tens of nats a
    # step; instead the step scores nothing, the residual built so far stays, and the free run starts again from the
    # measured velocity at the next step on the grid
    shipped = load_response()
    keep = np.abs(shipped.omega_ref) <= 1.0 + 1e-9
    narrow = TerrainResponse(shipped.v_ref, shipped.omega_ref[keep], shipped.terrains, shipped.steady[:, :, keep],
                             shipped.rate)
    path = tmp_path / "narrow.yaml"
    path.write_text(narrow.to_yaml())
    model = shipped_model()
    est = make_estimator(model, EstimatorConfig(response_file=str(path)))
    assert isinstance(est, BayesTerrainEstimator)
    for row in _held_drive("tile", (1.0, 0.6), 5.0, seed=7):
        est.observe(*row)
    built = est._response_residual.copy()
    assert np.any(built != 0.0)
    x, _, x1 = _held_drive("tile", (1.0, 1.6), 3.0, seed=7)[-1]
    u_off = np.array([1.0, 1.6])
    np.testing.assert_array_equal(est._response_loglik(x, u_off, x1, np.zeros(2), False), np.zeros(3))
    np.testing.assert_array_equal(est._response_residual, built)
    assert est._response_pred is None
    u_on = np.array([1.0, 0.9])
    est._response_loglik(x1, u_on, x1, u_on - u_off, False)
    np.testing.assert_allclose(est._response_pred, narrow.select(list(model.terrains)).step(np.tile(x1[3:5], (3, 1)),
                                                                                         u_on))


def _start_from_rest(terrain: str, accel: float, seed: int) -> list:
    """(state, command, next state) steps of the physics plant (sensor noise on) starting from rest under a v command
    ramped at `accel` [m/s^2] to 1.5 m/s, straight, for 1.5 s: the start of every closed-loop run."""
    plant = PhysicsPlant(load_terrains(), terrain, seed=seed)
    plant.reset(np.zeros(5))
    x = plant.measure()
    rows = []
    for k in range(15):
        u = np.array([min(1.5, accel * 0.1 * (k + 1)), 0.0])
        plant.step(u, 0.1)
        x1 = plant.measure()
        rows.append((x, u, x1))
        x = x1
    return rows


UNGATED = {"response_max_transient": (float("inf"), float("inf")), "gp_max_speed_gap": float("inf")}


@pytest.mark.parametrize("terrain", ["grass", "tile"])
@pytest.mark.parametrize("accel", [1.5, 3.0])
def test_a_start_from_rest_is_not_read_as_asphalt(terrain: str, accel: float) -> None:
    # while the robot accelerates from rest its PI integrators and torque limit are far from where the GP and the
    # response were fitted: scored anyway, the first 1.5 s read as asphalt on every terrain (ungated below); gated
    # (the default), they add little evidence and none of it points away from the terrain driven on
    model = shipped_model()
    i_true, i_asphalt = list(model.terrains).index(terrain), list(model.terrains).index("asphalt")
    posteriors = {}
    for name, fields in (("default", {}), ("ungated", UNGATED)):
        est = make_estimator(model, EstimatorConfig(**fields))
        assert isinstance(est, BayesTerrainEstimator)
        for seed in range(3):
            est.reset()
            for row in _start_from_rest(terrain, accel, seed):
                est.observe(*row)
            posteriors.setdefault(name, []).append(est._posterior.copy())
    if accel == 1.5:  # the planner's own start; a faster ramp is torque-limited on grass and reads less one-sided
        for p in posteriors["ungated"]:
            assert p[i_asphalt] > p[i_true] + 0.02, p
    for p in posteriors["default"]:
        assert p[i_asphalt] <= 0.4 and p[i_asphalt] < p[i_true] + 0.03, p


def test_the_start_gates_score_nothing_until_the_robot_is_up_to_speed() -> None:
    model = shipped_model()
    est = make_estimator(model)
    ungated = make_estimator(model, EstimatorConfig(**UNGATED))
    assert isinstance(est, BayesTerrainEstimator) and isinstance(ungated, BayesTerrainEstimator)
    rows = _start_from_rest("tile", 100.0, seed=1)  # a step command: 1.5 m/s from the first step
    for x, u, x1 in rows[:3]:  # the response's warm-up: the GP evidence alone, which the speed gap gates
        assert u[0] - x[3] > est.config.gp_max_speed_gap
        est.observe(x, u, x1)
        ungated.observe(x, u, x1)
    np.testing.assert_array_equal(est._posterior, np.full(3, 1.0 / 3.0))
    assert not np.allclose(ungated._posterior, 1.0 / 3.0)
    x, u, x1 = rows[3]
    response = load_response().select(list(model.terrains))
    assert np.max(np.abs(response.steady_at(u)[:, 0] - x1[3])) > est.config.response_max_transient[0]
    est.observe(x, u, x1)
    np.testing.assert_array_equal(est._response_pred[:, 0], np.full(3, x1[3]))  # v's free run restarts from here
    np.testing.assert_array_equal(est._response_residual[:, 0], np.zeros(3))  # and nothing of v is scored yet
    for row in rows[4:]:
        est.observe(*row)
    x, u, x1 = rows[-1]
    assert np.max(np.abs(response.steady_at(u)[:, 0] - x1[3])) <= est.config.response_max_transient[0]
    assert np.any(est._response_residual[:, 0] != 0.0)  # up to speed, v's response is scored again


def test_the_response_settles_after_a_start_before_it_is_scored() -> None:
    # response_settle_steps: after the last step the start gate held, the response's free run and average go on but
    # add no evidence for that many steps (the swerves right after a start, which its first-order omega misreads);
    # until then the posterior is the GP evidence's alone, after it the response speaks
    model = shipped_model()
    rows = _start_from_rest("asphalt", 100.0, seed=2)  # a step command: the gate holds the first steps
    rows += _held_drive_from(rows[-1][2], "asphalt", (1.5, -0.8), 3.0, seed=2)
    settled = make_estimator(model, EstimatorConfig(response_settle_steps=12))
    gp_only = make_estimator(model, EstimatorConfig(response="none"))
    scored = make_estimator(model)
    assert all(isinstance(e, BayesTerrainEstimator) for e in (settled, gp_only, scored))
    opened = next(k for k, (x, u, _) in enumerate(rows) if u[0] - x[3] <= settled.config.gp_max_speed_gap)
    for k, row in enumerate(rows):
        for est in (settled, gp_only, scored):
            est.observe(*row)
        if k < opened + 11:  # the step the gate opens is the first of the 12
            np.testing.assert_allclose(settled._posterior, gp_only._posterior, rtol=1e-12, atol=1e-15)
    assert not np.allclose(settled._posterior, gp_only._posterior, atol=1e-3)  # settled: the response speaks
    assert not np.allclose(scored._posterior, gp_only._posterior, atol=1e-3)


def _held_drive_from(x0: np.ndarray, terrain: str, command: tuple[float, float], seconds: float, seed: int) -> list:
    """As `_held_drive`, from the measured state `x0` (the plant set there, noise-free)."""
    plant = PhysicsPlant(load_terrains(), terrain, seed=seed)
    plant.reset(np.asarray(x0, dtype=np.float64))
    u = np.asarray(command, dtype=np.float64)
    x = np.asarray(x0, dtype=np.float64)
    rows = []
    for _ in range(int(round(seconds / 0.1))):
        plant.step(u, 0.1)
        x1 = plant.measure()
        rows.append((x, u, x1))
        x = x1
    return rows
