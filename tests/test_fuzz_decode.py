"""Property-based fuzzing of the pure decoders, in process (cheap, so many examples): `schemas.decode` for every
message model, the ROS 2 Odometry CDR decoder, and egress's `Safety` and ingress's checks on extreme values.

Deterministic: derandomized, no example database. Each property: a decoder either returns a valid, finite
message or raises its documented error (DecodeError / ValueError), never anything else."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import pytest
from fuzz_strategies import extreme_tasks, floats, materialize, payloads, valid_state
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas import BaseCommand, Command, DecodeError, State, Task, decode
from schemas.messages import MODELS, READABLE_VERSIONS
from services.codec import ros2

FUZZ = settings(
    max_examples=80, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck)
)


def finite_everywhere(value: Any) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, dict):
        return all(finite_everywhere(v) for v in value.values())
    if isinstance(value, list | tuple):
        return all(finite_everywhere(v) for v in value)
    return True


@pytest.mark.parametrize("name", sorted(MODELS))
def test_decode_returns_a_finite_message_or_a_decode_error(name: str) -> None:
    model = MODELS[name]
    extreme = valid_state() if model is State else extreme_tasks if model is Task else None

    @FUZZ
    @given(payload=payloads(model, extreme))
    def check(payload: bytes | dict) -> None:
        data = materialize(payload)
        try:
            msg = decode(model, data)
        except DecodeError as exc:
            assert str(exc).startswith(model.__name__), exc  # the error names the message type
            return
        assert isinstance(msg, model)
        assert finite_everywhere(msg.model_dump()), data[:200]
        assert msg.header.schema_version in READABLE_VERSIONS

    check()


# a valid Odometry to mutate: the decoder sees truncations, bit flips and extreme values of real messages
_ODOM = ros2.odometry_cdr(np.array([1.0, 2.0, 0.3, 0.5, 0.1]), 1_700_000_000_000_000_000)


@st.composite
def cdr_payloads(draw: st.DrawFn) -> bytes:
    kind = draw(st.sampled_from(["random", "truncated", "flipped", "extended", "values"]))
    if kind == "random":
        return draw(st.binary(max_size=800))
    if kind == "truncated":
        return _ODOM[: draw(st.integers(0, len(_ODOM) - 1))]
    if kind == "flipped":
        data = bytearray(_ODOM)
        for _ in range(draw(st.integers(1, 8))):
            i = draw(st.integers(0, len(data) - 1))
            data[i] ^= 1 << draw(st.integers(0, 7))
        return bytes(data)
    if kind == "extended":
        return _ODOM + draw(st.binary(min_size=1, max_size=64))
    state = np.array([draw(floats) for _ in range(5)])
    return ros2.odometry_cdr(state, draw(st.integers(0, 2**63 - 1)))


@FUZZ
@given(data=cdr_payloads())
def test_ros2_odometry_decoder_returns_a_reading_or_a_value_error(data: bytes) -> None:
    try:
        reading = ros2.odometry_from_cdr(data)
    except ValueError as exc:
        assert "Odometry" in str(exc) or "CDR" in str(exc), exc
        return
    assert reading.state.shape == (5,)
    assert reading.covariance is None or reading.covariance.shape == (5, 5)
    assert isinstance(reading.frame_id, str) and reading.stamp_ns >= 0


@FUZZ
@given(commands=st.lists(st.tuples(floats, floats, st.floats(0.0, 2.0)), min_size=1, max_size=30),
       estop=st.lists(st.booleans(), min_size=1, max_size=30))
def test_egress_safety_output_is_finite_and_within_limits_for_any_command(
    commands: list[tuple[float, float, float]], estop: list[bool]
) -> None:
    from gpmppi.safety import Safety
    from services.egress import Settings

    s = Settings()
    safety = Safety(s)
    now = 0.0
    for i, (v, w, dt) in enumerate(commands):
        now += dt
        if not (math.isfinite(v) and math.isfinite(w)):
            continue  # the Command schema refuses these before egress sees them (checked above)
        safety.estop = estop[i % len(estop)]
        now_ns = int(now * 1e9)
        safety.on_command(v, w, now_ns, now, now_ns)  # stamped now: fresh
        out = safety.output(now)  # egress's clock is monotonic: time never goes back
        assert math.isfinite(out.v) and math.isfinite(out.omega), (v, w, out)
        assert s.v_limits[0] - 1e-9 <= out.v <= s.v_limits[1] + 1e-9 and abs(out.omega) <= s.omega_limit + 1e-9
        if safety.estop:
            assert (out.v, out.omega, out.reason) == (0.0, 0.0, "estop")
        msg = BaseCommand(v=out.v, omega=out.omega, reason=out.reason)  # what egress publishes validates
        assert decode(BaseCommand, msg.model_dump_json().encode()) == msg


@FUZZ
@given(state=st.lists(floats, min_size=5, max_size=5), age_s=st.sampled_from([-10.0, -0.1, 0.0, 0.1, 0.4, 0.6, 1e6]))
def test_ingress_check_refuses_non_finite_implausible_stale_and_future_input(state: list[float], age_s: float) -> None:
    from services.ingress import Ingress, Settings

    s = Settings()
    ingress = Ingress(s, node=None)  # type: ignore[arg-type] - check() does not touch the node
    now = time.time_ns()
    stamp = max(0, now - int(age_s * 1e9))
    x = np.array(state)
    reason = ingress.check(stamp, x, now)
    ok = (
        bool(np.all(np.isfinite(x)))
        and abs(x[3]) <= s.max_speed
        and abs(x[4]) <= s.max_yaw_rate
        and -s.max_future_s <= age_s <= s.max_age_s
    )
    assert (reason is None) == ok, (state, age_s, reason)


def test_command_schema_refuses_non_finite_values() -> None:
    for bad in ("NaN", "Infinity", "-Infinity", "1e999"):
        with pytest.raises(DecodeError):
            decode(Command, f'{{"v_ref": {bad}, "omega_ref": 0}}'.encode())


@pytest.mark.parametrize(
    "v, omega, x",
    [(-5.0, 20.0, None), (-212.5, 0.0, None), (0.0, 0.0, 1e308), (0.0, 1e6, None)],
    ids=["v-5_omega20_ingress_passes_it", "v-212", "x1e308", "omega1e6"],
)
def test_planner_service_publishes_nothing_non_finite_for_an_extreme_state(v: float, omega: float, x: float | None
                                                                          ) -> None:
    """For a finite but extreme state the rollouts may diverge (the model knows nothing out there): the service
    then sends no command (`plan_is_finite` is what it checks), and whatever it does send decodes."""
    from gpmppi.mppi.cycle import plan_is_finite
    from gpmppi.mppi.planner import Planner, PlannerConfig
    from services.planner import load_model, load_scenario
    from services.planner_outputs import plan_message

    scenario = load_scenario("circle")
    planner = Planner(PlannerConfig(), load_model(None))
    state = np.array([*scenario.start[:3], v, omega], dtype=np.float64)  # at the lane's start
    state[0] = state[0] if x is None else x
    result = planner.plan(state, scenario.task, delay_s=0.01)
    if not plan_is_finite(result):
        return  # refused: no command, no plan (counted as plan_nonfinite)
    command = Command(v_ref=float(result.control[0]), omega_ref=float(result.control[1]))
    decode(Command, command.model_dump_json().encode())
    plan = plan_message(result, time.time_ns(), scenario.task, 16)
    try:
        decode(type(plan), plan.model_dump_json().encode())  # what the planner's publisher checks
    except DecodeError as exc:  # the service counts it (plan_invalid) and publishes no Plan; the command is finite
        assert "Plan" in str(exc)
