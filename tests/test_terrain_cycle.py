"""The terrain service's cycle (`gpmppi.terrain.cycle.TerrainCycle`) with the real estimator and shipped model and
explicit times: pairing by stamp whatever the arrival order, dt gating, the wait for the newest state's command,
clean-up; and bad settings named by file and field (the cycle's, egress's safety, a launch file's)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from cached_models import shipped_model
from pydantic import ValidationError

from gpmppi.evaluation.deployed import DeployFileError, deployed_path
from gpmppi.safety import SafetyConfig
from gpmppi.terrain.cycle import TerrainCycle, TerrainCycleConfig
from gpmppi.terrain.estimator import make_estimator
from gpmppi.terrain.settings import EstimatorConfig

NS = 1_000_000_000
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def model():
    return shipped_model()


def _cycle(model, **config: object) -> TerrainCycle:
    return TerrainCycle(TerrainCycleConfig(**config), len(model.terrains), make_estimator(model, EstimatorConfig()),
                        record_pairs=True)


def _state(k: int) -> np.ndarray:
    return np.array([0.1 * k, 0.0, 0.0, 1.0 + 0.01 * k, 0.05])


def test_pairs_each_transition_with_the_command_of_its_first_state_whatever_the_arrival_order(model) -> None:
    c = _cycle(model, pairing="stamp")
    c.on_states([(0, _state(0))], 0.0)
    c.on_command(0, [1.0, 0.1])
    assert c.wait_s(0.0) == 0.0  # the newest state's command is in: solve now
    first = c.solve()
    assert not first.ok and first.observed == 0 and first.stamp_ns == 0  # one state: no transition yet
    # the next command arrives before its state (a late loop): still paired by stamp, not by order
    c.on_command(2 * NS // 10, [1.2, 0.3])
    c.on_states([(NS // 10, _state(1)), (2 * NS // 10, _state(2))], 0.2)
    c.on_command(NS // 10, [1.1, 0.2])
    update = c.solve()
    assert update.observed == 2 and update.stamp_ns == 2 * NS // 10
    assert c.pairs is not None
    assert [(s, u.tolist()) for s, u in c.pairs] == [(0, [1.0, 0.1]), (NS // 10, [1.1, 0.2])]
    # clean-up: only the newest state's command is kept (the next transition starts there)
    assert list(c.commands) == [2 * NS // 10]
    assert np.isclose(update.weights.sum(), 1.0) and np.all(update.weights >= 0.0)


def test_transitions_off_dt_or_without_a_command_are_skipped(model) -> None:
    c = _cycle(model, dt=0.1, dt_tolerance=0.5, pairing="stamp")
    c.on_states([(0, _state(0))], 0.0)
    c.on_command(0, [1.0, 0.0])
    c.solve()
    # 0.16 s later: more than 50 % off dt = 0.1 s, a lost state
    c.on_states([(16 * NS // 100, _state(1))], 0.16)
    c.on_command(16 * NS // 100, [1.0, 0.0])
    gap = c.solve()
    assert (gap.observed, gap.skipped) == (0, 1) and c.counts == {"gap_off_dt": 1}
    # 0.1 s later: its command (stamped 0.26 s) never comes, so the cycle waits command_wait_s, then solves the
    # transition from 0.16 s (whose command it kept)
    c.on_states([(26 * NS // 100, _state(2))], 0.26)
    assert c.wait_s(0.26) == pytest.approx(0.05)
    assert c.wait_s(0.30) == pytest.approx(0.01)
    assert c.wait_s(0.32) == 0.0
    assert c.solve().observed == 1
    # the next transition starts at the state whose command never came: skipped
    c.on_states([(36 * NS // 100, _state(3))], 0.36)
    c.on_command(36 * NS // 100, [1.0, 0.0])
    assert c.wait_s(0.36) == 0.0
    out = c.solve()
    assert (out.observed, out.skipped) == (0, 1) and c.counts == {"gap_off_dt": 1, "no_command": 1}


def test_applied_pairing_averages_what_the_base_held_over_each_transition(model) -> None:
    """Each state's command reaches the base 30 ms after the state: over the first 30 ms of a step the base still
    holds the previous command."""
    c = _cycle(model, pairing="applied")
    ms = NS // 1000
    c.on_output(-20 * ms, [0.5, 0.0])  # the command before the first state, held from -20 ms
    for k, u in enumerate([[1.0, 0.0], [2.0, 0.2], [2.0, 0.2]]):
        c.on_states([(100 * k * ms, _state(k))], 0.1 * k)
        c.on_command(100 * k * ms, u)  # paired by stamp: the base got the state's command
        c.on_output((100 * k + 30) * ms, u)
        if k == 1:
            c.on_output(180 * ms, [1.5, 0.1])  # a limited repeat of egress, 20 ms before the next state
        c.solve()
    assert c.pairs is not None
    (s0, u0), (s1, u1) = c.pairs
    assert (s0, s1) == (0, 100 * ms)
    assert np.allclose(u0, [0.03 * 0.5 + 0.07 * 1.0, 0.0] / np.float64(0.1))
    assert np.allclose(u1, [(0.03 * 1.0 + 0.05 * 2.0 + 0.02 * 1.5) / 0.1, (0.05 * 0.2 + 0.02 * 0.1) / 0.1])
    assert [t for t, _ in c.outputs] == [180 * ms, 230 * ms]  # clean-up keeps what the base held at 200 ms on
    with pytest.raises(ValidationError, match="needs command_source 'base_cmd'"):
        TerrainCycleConfig(pairing="applied", command_source="cmd")


def test_a_base_with_ticks_takes_an_output_at_its_first_tick_after_the_arrival(model) -> None:
    """The sim steps its plant at 100 Hz in phase with the states it publishes: an output that arrives 12 ms after
    a state acts from 20 ms, one at exactly a tick from that tick."""
    ms = NS // 1000
    c = _cycle(model, base_period_s=0.01)
    c.on_states([(1000 * ms, _state(0))], 1.0)
    c.on_output(1012 * ms, [1.0, 0.0])
    c.on_output(1030 * ms, [2.0, 0.0])
    c.on_output(1030 * ms + 1, [3.0, 0.0])
    assert [t for t, _ in c.outputs] == [1020 * ms, 1030 * ms, 1040 * ms]
    free = _cycle(model)
    free.on_states([(1000 * ms, _state(0))], 1.0)
    free.on_output(1012 * ms, [1.0, 0.0])
    assert [t for t, _ in free.outputs] == [1012 * ms]
    with pytest.raises(ValidationError, match="base_period_s"):
        TerrainCycleConfig(base_period_s=0.5)


def test_the_prior_goes_out_before_the_estimator_exists(model) -> None:
    c = TerrainCycle(TerrainCycleConfig(), len(model.terrains))
    assert c.wait_s(0.0) == float("inf")
    c.on_states([(5, _state(0))], 0.0)
    prior = c.prior_update(identified=False)
    assert prior.stamp_ns == 5 and not prior.ok and np.allclose(prior.weights, 1 / len(model.terrains))
    assert not prior.identified and c.prior_update(identified=True).identified
    with pytest.raises(RuntimeError, match="no estimator yet"):
        c.solve()


# ---- bad settings ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("field", "value", "says"), [
    ("dt", 0.0, "greater than 0"),
    ("dt_tolerance", 1.5, "less than 1"),
    ("command_source", "odom", "'base_cmd' or 'cmd'"),
    ("command_wait_s", -0.1, "greater than or equal to 0"),
])
def test_terrain_cycle_settings_out_of_range_are_refused_by_name(field: str, value: object, says: str) -> None:
    with pytest.raises(ValidationError) as info:
        TerrainCycleConfig(**{field: value})
    assert field in str(info.value) and says in str(info.value)


def _launch(tmp_path: Path, egress: dict, terrain: dict) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"robot": "r", "services": [
        {"name": "terrain", "config": terrain}, {"name": "planner"}, {"name": "egress", "config": egress}]}))
    return path


def test_a_launch_files_bad_egress_or_terrain_setting_names_the_file_and_field(tmp_path: Path) -> None:
    path = _launch(tmp_path, {"output": "sim", "accel_limit": -2.0}, {})
    with pytest.raises(DeployFileError) as info:
        deployed_path(path)
    msg = str(info.value)
    assert str(path) in msg and "services[2] (egress).config.accel_limit" in msg and "greater than 0" in msg
    path = _launch(tmp_path, {}, {"command_source": "base_command"})
    with pytest.raises(DeployFileError) as info:
        deployed_path(path)
    msg = str(info.value)
    assert "services[0] (terrain).config.command_source" in msg and "'base_cmd' or 'cmd'" in msg
    assert "'base_command'" in msg
    path = _launch(tmp_path, {"v_limits": [0.2, 1.0]}, {"estimator": {"switch_prob": 2.0}})
    with pytest.raises(DeployFileError, match=r"\(egress\).config: Value error, v_limits \[0.2, 1.0\] must include 0"):
        deployed_path(path)
    with pytest.raises(DeployFileError, match="does not exist"):
        deployed_path(tmp_path / "missing.yaml")


def test_the_shipped_launch_files_give_their_limits_and_sources() -> None:
    robot = deployed_path(REPO / "deploy" / "robot.yaml")
    assert robot.safety is not None and (robot.safety.accel_limit, robot.safety.decel_limit) == (2.0, 4.0)
    assert robot.safety.v_limits == (0.0, 2.0) and robot.terrain.command_source == "base_cmd"
    sim = deployed_path(REPO / "deploy" / "sim.yaml")
    # the sim's steps; each 10 Hz command ramped over its period
    assert sim.safety == SafetyConfig(command_ramp_s=0.1) and sim.terrain == TerrainCycleConfig(base_period_s=0.01)


def test_the_services_settings_carry_the_cycles_checks() -> None:
    from services.egress import Settings as EgressSettings
    from services.terrain import Settings as TerrainSettings

    with pytest.raises(ValidationError, match="command_source"):
        TerrainSettings(command_source="planner")
    with pytest.raises(ValidationError, match="watchdog_timeout_s"):
        EgressSettings(watchdog_timeout_s=0.0)
    assert TerrainCycleConfig.from_settings(TerrainSettings(dt=0.2)).dt == 0.2
    assert SafetyConfig.from_settings(EgressSettings(jerk_limit=3.0)).jerk_limit == 3.0


@pytest.mark.parametrize(("service", "config", "says"), [
    ("terrain", {"command_source": "odom"}, "services[0] (terrain).config.command_source: Input should be 'base_cmd'"),
    ("terrain", {"dt_tolerance": 2.0}, "services[0] (terrain).config.dt_tolerance: Input should be less than 1"),
    ("egress", {"decel_limit": 0.0}, "services[0] (egress).config.decel_limit: Input should be greater than 0"),
    ("egress", {"watchdog_timeout_s": -1}, "services[0] (egress).config.watchdog_timeout_s"),
])
def test_gpmppi_launch_refuses_a_bad_setting_before_starting_anything(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], service: str, config: dict, says: str
) -> None:
    from services.launch.launcher import main

    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"router": {"enabled": False}, "services": [{"name": service, "config": config}]}))
    assert main([str(path)]) == 2
    err = capsys.readouterr().err
    assert f"{path}:" in err and says in err, err  # the file with the line of the setting


@pytest.mark.parametrize("first_top", ["tie", "established"])
def test_the_published_weights_say_whether_they_name_a_top(model, first_top: str) -> None:
    """The terrain service's message carries the estimator's `identified` (TerrainWeights schema 6): with `first_top:
    established` the uniform start names no top; with `tie` (before it, and every other estimator) it always does."""
    from schemas.codec import decode, encode
    from schemas.messages import TerrainWeights
    from services.terrain import _weights_message

    estimator = make_estimator(model, EstimatorConfig(first_top=first_top))
    c = TerrainCycle(TerrainCycleConfig(pairing="stamp"), len(model.terrains), estimator)
    updates = []
    for k in range(4):
        c.on_states([(k * NS // 10, _state(k))], 0.1 * k)
        c.on_command(k * NS // 10, [1.0, 0.1])
        updates.append(c.solve())
    assert [u.identified for u in updates] == [first_top == "tie"] * 4
    # the service's first message, the prior it publishes while it builds the estimator, says the same: with
    # `established` it named the tie's first ground, and the stack's metric counted the first identification of any
    # other ground as a change of the top (a 40 s launch on grass: 1.6 changes a minute, none of them the filter's)
    config = EstimatorConfig(first_top=first_top)
    assert config.names_top_at_start is (first_top == "tie")
    assert EstimatorConfig(method="paper").names_top_at_start
    starting = TerrainCycle(TerrainCycleConfig(), len(model.terrains))
    starting.on_states([(5, _state(0))], 0.0)
    updates.insert(0, starting.prior_update(config.names_top_at_start))
    assert updates[0].identified is (first_top == "tie")
    for u in updates:
        back = decode(TerrainWeights, encode(_weights_message(list(model.terrains), u)))
        assert back.identified is u.identified and np.allclose(back.weights, u.weights)
