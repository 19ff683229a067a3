"""Messages: JSON round trip, non-finite and wrong versions rejected, key -> model registry, schema export."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from typer.testing import CliRunner

from schemas import (
    KEYS,
    BaseCommand,
    Circle,
    Command,
    DecodeError,
    EStop,
    Header,
    Heartbeat,
    Plan,
    State,
    Task,
    TerrainLabel,
    TerrainWeights,
    decode,
    encode,
    key_for,
    model_for_key,
)
from schemas.messages import MODELS, SCHEMA_VERSION

EXAMPLES = [
    State(
        header=Header(stamp_ns=5, frame_id="odom", seq=3),
        x=1.0,
        y=-2.0,
        theta=0.5,
        v=1.2,
        omega=-0.1,
        covariance=[0.0] * 25,
    ),
    Command(v_ref=1.0, omega_ref=0.25),
    BaseCommand(v=0.0, omega=0.0, reason="watchdog"),
    TerrainLabel(terrain="grass"),
    TerrainWeights(names=["asphalt", "grass"], weights=[0.3, 0.7], solver_ok=False, residual=0.5),
    TerrainWeights(names=["asphalt", "grass"], weights=[0.6, 0.4], unknown=0.875, unknown_active=True),
    TerrainWeights(names=["asphalt", "grass"], weights=[0.6, 0.4], unknown=0.875, unknown_active=True,
                   unknown_channel="free-run"),
    Task(kind="lane", centerline=[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]], half_width=1.0),
    Task(kind="goal", goal=[7.0, 5.0], obstacles=[Circle(x=1.0, y=2.0, r=0.5)]),
    Plan(
        command=Command(v_ref=1.0, omega_ref=0.0),
        controls=[[1.0, 0.0]],
        states=[[0.0] * 5, [0.1] * 5],
        cov_xy=[[0.1, 0.0, 0.1]],
        tightened=[1.5],
        samples=[[[0.0, 0.0], [1.0, 1.0]]],
        timings_ms={"total": 3.0},
        critic_costs={"deviation": 2.5, "variance": 0.125},
    ),
    Heartbeat(service="planner", rate_hz=10.0, received=5, rejected=1, published=4, last_error="x"),
    EStop(engaged=True, reason="button"),
]


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip(msg) -> None:
    data = encode(msg)
    assert json.loads(data)["header"]["schema_version"] == SCHEMA_VERSION
    assert decode(type(msg), data) == msg


def test_every_message_has_the_header_fields() -> None:
    for model in MODELS.values():
        header = model.model_fields["header"].annotation
        assert header is Header
    assert set(Header.model_fields) == {"stamp_ns", "frame_id", "seq", "schema_version"}


@pytest.mark.parametrize("bad", ["NaN", "Infinity", "-Infinity", "1e400"])
def test_non_finite_rejected(bad: str) -> None:
    with pytest.raises(DecodeError, match="v_ref"):
        decode(Command, f'{{"v_ref": {bad}, "omega_ref": 0.0}}'.encode())
    with pytest.raises(ValueError):
        State(x=math.nan, y=0, theta=0, v=0, omega=0)
    with pytest.raises(ValueError):
        TerrainWeights(names=["a"], weights=[math.inf])


def test_wrong_schema_version_rejected() -> None:
    data = json.loads(encode(Command(v_ref=0.0, omega_ref=0.0)))
    data["header"]["schema_version"] = SCHEMA_VERSION + 1
    with pytest.raises(DecodeError, match="schema_version"):
        decode(Command, json.dumps(data).encode())


def test_a_version_1_command_still_decodes_and_only_version_2_names_its_process() -> None:
    old = b'{"header": {"schema_version": 1, "stamp_ns": 5}, "v_ref": 1.0, "omega_ref": 0.0}'
    msg = decode(Command, old)
    assert msg.header.schema_version == 1 and msg.source == ""
    assert decode(Command, encode(Command(v_ref=1.0, omega_ref=0.0, source="abc"))).source == "abc"
    with pytest.raises(DecodeError, match="source"):
        decode(Command, b'{"header": {"schema_version": 1}, "v_ref": 1.0, "omega_ref": 0.0, "source": "abc"}')


def test_older_terrain_weights_decode_as_known_ground_and_only_version_3_says_unknown() -> None:
    for version in (1, 2):
        old = f'{{"header": {{"schema_version": {version}}}, "names": ["a", "b"], "weights": [0.5, 0.5]}}'.encode()
        msg = decode(TerrainWeights, old)
        assert msg.header.schema_version == version and msg.unknown == 0.0 and not msg.unknown_active
        bad = json.loads(old)
        bad["unknown"] = 0.7
        with pytest.raises(DecodeError, match="schema_version 3"):
            decode(TerrainWeights, json.dumps(bad).encode())
    new = decode(TerrainWeights, encode(TerrainWeights(names=["a"], weights=[1.0], unknown=0.7, unknown_active=True)))
    assert new.header.schema_version >= 3 and new.unknown == 0.7 and new.unknown_active
    for bad_p in (-0.1, 1.5):
        with pytest.raises(DecodeError, match="unknown"):
            decode(TerrainWeights, f'{{"names": ["a"], "weights": [1.0], "unknown": {bad_p}}}'.encode())


def test_bad_payloads_name_the_problem() -> None:
    with pytest.raises(DecodeError, match="Command"):
        decode(Command, b"{nope")
    with pytest.raises(DecodeError, match="extra|unknown|not permitted"):
        decode(Command, b'{"v_ref": 1, "omega_ref": 0, "turbo": true}')
    with pytest.raises(DecodeError, match="exceeds"):
        decode(Command, b" " * 100, max_bytes=10)
    with pytest.raises(DecodeError, match="simplex"):
        decode(TerrainWeights, b'{"names": ["a", "b"], "weights": [0.9, 0.9]}')


def test_key_to_model_registry() -> None:
    assert model_for_key("gpmppi/jackal/state") is State
    assert model_for_key("gpmppi/other/odom/raw") is State
    assert model_for_key("gpmppi/jackal/health/planner") is Heartbeat
    assert model_for_key("gpmppi/jackal/base/cmd") is BaseCommand
    assert model_for_key(key_for("terrain_weights", "r2")) is TerrainWeights
    for name, (_, model) in KEYS.items():
        assert model_for_key(key_for(name, "rx", "svc")) is model
    with pytest.raises(KeyError):
        model_for_key("gpmppi/jackal/unknown")
    with pytest.raises(KeyError):
        key_for("nope")


def test_schemas_export(tmp_path: Path) -> None:
    from tools.cli import app

    result = CliRunner().invoke(app, ["schemas", "export", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    files = {p.name for p in (tmp_path / "out").iterdir()}
    assert files == {f"{name}.schema.json" for name in MODELS} | {"keys.json"}
    schema = json.loads((tmp_path / "out" / "State.schema.json").read_text())
    assert schema["title"] == "State" and "header" in schema["properties"]
    keys = json.loads((tmp_path / "out" / "keys.json").read_text())
    assert keys["gpmppi/{robot}/health/{service}"] == "Heartbeat"


def test_plans_say_their_model_version_from_schema_version_4() -> None:
    from schemas import Plan

    old = {"header": {"schema_version": 3}, "command": {"v_ref": 0.0, "omega_ref": 0.0}, "controls": [[0.0, 0.0]],
           "states": [[0.0] * 5]}
    assert decode(Plan, json.dumps(old).encode()).model_version == 0
    with pytest.raises(DecodeError, match="schema_version 4"):
        decode(Plan, json.dumps({**old, "model_version": 2}).encode())
    plan = decode(Plan, encode(Plan(**{k: v for k, v in old.items() if k != "header"}, model_version=2)))
    assert plan.model_version == 2 and plan.header.schema_version >= 4


def test_terrain_weights_name_the_channel_from_schema_version_5_and_older_ones_read_as_not_said() -> None:
    for version in (1, 2, 3, 4):  # as recorded or sent by the builds before the field
        fields = '"unknown": 0.9, "unknown_active": true, ' if version >= 3 else ""
        old = (f'{{"header": {{"schema_version": {version}}}, "names": ["a", "b"], "weights": [0.5, 0.5], '
               f'{fields}"solver_ok": true}}').encode()
        msg = decode(TerrainWeights, old)
        assert msg.header.schema_version == version and msg.unknown_channel == ""
        assert msg.unknown == (0.9 if version >= 3 else 0.0)
        bad = json.loads(old)
        bad["unknown_channel"] = "free-run"
        with pytest.raises(DecodeError, match="unknown_channel is a schema_version 5 field"):
            decode(TerrainWeights, json.dumps(bad).encode())
    for channel in ("one-step", "free-run", ""):
        sent = TerrainWeights(names=["a"], weights=[1.0], unknown=0.9, unknown_active=True, unknown_channel=channel)
        back = decode(TerrainWeights, encode(sent))
        assert back.header.schema_version >= 5 and back.unknown_channel == channel
        assert json.loads(encode(sent))["unknown_channel"] == channel
    with pytest.raises(DecodeError, match="unknown_channel"):  # only the two channels there are
        decode(TerrainWeights, b'{"names": ["a"], "weights": [1.0], "unknown_channel": "gut"}')
    schema = TerrainWeights.model_json_schema()["properties"]["unknown_channel"]
    assert schema["enum"] == ["", "one-step", "free-run"] and "grip" in schema["description"]


def test_terrain_weights_say_whether_they_name_a_top_from_schema_version_6_and_older_ones_read_as_named() -> None:
    """`identified` (schema 6): an estimator that names no top ground until the evidence establishes one says so;
    older messages, recorded or sent before the field, read as naming their argmax (what their builds meant)."""
    for version in (1, 2, 3, 4, 5):
        old = f'{{"header": {{"schema_version": {version}}}, "names": ["a", "b"], "weights": [0.5, 0.5]}}'.encode()
        msg = decode(TerrainWeights, old)
        assert msg.header.schema_version == version and msg.identified
        bad = json.loads(old)
        bad["identified"] = False
        with pytest.raises(DecodeError, match="identified is a schema_version 6 field"):
            decode(TerrainWeights, json.dumps(bad).encode())
    for identified in (False, True):
        sent = TerrainWeights(names=["a", "b"], weights=[0.6, 0.4], identified=identified)
        back = decode(TerrainWeights, encode(sent))
        assert back.header.schema_version == 6 and back.identified is identified
    assert "no identification" in TerrainWeights.model_json_schema()["properties"]["identified"]["description"]
