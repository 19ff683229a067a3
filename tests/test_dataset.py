"""`gpmppi dataset`: excitation over terrains recorded to MCAP, and the in-memory array form."""

from __future__ import annotations

import json
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from typer.testing import CliRunner

from gpmppi.plant import load_terrains
from gpmppi.plant.excitation import Excitation, runs_to_series, simulate_dataset
from schemas.messages import Command, Header, State, TerrainLabel
from services.recording.mcap_writer import McapWriter
from tools.cli import app
from tools.dataset import read_dataset

DISTANCE = 50.0


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ds") / "data.mcap"
    result = CliRunner().invoke(app, ["dataset", "-o", str(out), "--distance", str(DISTANCE), "--seed", "3"])
    assert result.exit_code == 0, result.output
    return out


def test_dataset_file_has_matched_ticks_keys_labels(small_dataset: Path) -> None:
    assert sorted(p.name for p in small_dataset.parent.iterdir()) == ["data.mcap"]  # no temporary left behind
    per_stamp: dict[int, Counter] = defaultdict(Counter)
    labels: dict[int, str] = {}
    with open(small_dataset, "rb") as f:
        reader = make_reader(f)
        topics = {c.topic for c in reader.get_summary().channels.values()}
        assert topics == {"gpmppi/jackal/state", "gpmppi/jackal/cmd", "gpmppi/jackal/terrain/label"}
        for schema, channel, message in reader.iter_messages():
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
            body = json.loads(message.data)
            stamp = body["header"]["stamp_ns"]
            assert message.log_time == stamp
            per_stamp[stamp][channel.topic] += 1
            values = [v for k, v in body.items() if k != "header" and isinstance(v, float)]
            assert np.all(np.isfinite(values))
            if channel.topic.endswith("label"):
                labels[stamp] = body["terrain"]
    assert all(c == Counter({"gpmppi/jackal/state": 1, "gpmppi/jackal/cmd": 1, "gpmppi/jackal/terrain/label": 1})
               for c in per_stamp.values())
    assert set(labels.values()) == {"tile", "asphalt", "grass"}
    # terrains follow one another on one timeline (grouped, in the order given)
    order = [labels[s] for s in sorted(labels)]
    assert [k for i, k in enumerate(order) if i == 0 or order[i - 1] != k] == ["tile", "asphalt", "grass"]


def test_dataset_reads_back_to_the_in_memory_arrays(small_dataset: Path) -> None:
    runs = read_dataset(small_dataset)
    direct = simulate_dataset(load_terrains(), ["tile", "asphalt", "grass"], distance=DISTANCE, seed=3)
    for name, run in direct.items():
        assert len(runs[name]) == 1
        back = runs[name][0]
        np.testing.assert_allclose(back.state, run.state, atol=1e-12)
        np.testing.assert_allclose(back.command, run.command, atol=1e-12)
        np.testing.assert_allclose(back.time, run.time, atol=1e-6)
        assert run.distance >= DISTANCE - 0.25  # the last tick's motion ends after its recorded state
        # sampled at dt = 0.1 s: positions move by at most ~v_max dt per tick
        assert np.max(np.hypot(*np.diff(run.true_state[:, :2], axis=0).T)) < 0.25


def test_labels_win_and_robot_must_match(small_dataset: Path) -> None:
    runs = read_dataset(small_dataset, terrain="ignored")  # labels win when present
    assert set(runs) == {"tile", "asphalt", "grass"}
    with pytest.raises(ValueError, match="wrong --robot"):
        read_dataset(small_dataset, robot="husky")


def test_unlabelled_log_needs_a_terrain_name(tmp_path: Path) -> None:
    """A real robot log has state + cmd only; it splits into segments at gaps in the stamps."""
    path = tmp_path / "robot.mcap"
    with McapWriter(path) as writer:
        for k in list(range(20)) + list(range(30, 45)):  # a 1 s gap after tick 19
            header = Header(stamp_ns=k * 100_000_000)
            writer.write("gpmppi/jackal/state", State(header=header, x=0, y=0, theta=0, v=0.1 * k, omega=0.0))
            writer.write("gpmppi/jackal/cmd", Command(header=header, v_ref=1.0, omega_ref=0.2))
    with pytest.raises(ValueError, match="no terrain labels"):
        read_dataset(path)
    runs = read_dataset(path, terrain="lawn")
    assert [len(r.command) for r in runs["lawn"]] == [20, 15]
    np.testing.assert_allclose(runs["lawn"][1].state[:, 3], 0.1 * np.arange(30, 45))


def test_dataset_rejects_unknown_terrain(tmp_path: Path) -> None:
    out = tmp_path / "x.mcap"
    result = CliRunner().invoke(app, ["dataset", "-o", str(out), "--terrain", "mud", "--distance", "5"])
    assert result.exit_code == 2
    assert "unknown terrain 'mud'" in result.output
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_excitation_covers_the_command_box() -> None:
    exc = Excitation(seed=0)
    cmds = np.vstack([exc.next_segment() for _ in range(400)])
    assert cmds[:, 0].min() >= 0 and cmds[:, 0].max() <= 2.0
    assert np.abs(cmds[:, 1]).max() <= np.pi
    hist, _, _ = np.histogram2d(cmds[:, 0], cmds[:, 1], bins=[4, 4], range=[[0, 2], [-np.pi, np.pi]])
    assert hist.min() > 0.01 * len(cmds)  # every cell of a 4x4 grid over the box is visited
    fast = (cmds[:, 0] > 1.2) & (np.abs(cmds[:, 1]) < 1.0)  # the planner's region is well covered
    assert fast.mean() > 0.2
    again = Excitation(seed=0)
    np.testing.assert_array_equal(again.next_segment(), Excitation(seed=0).next_segment())


def test_runs_to_series_matches_the_trainer_layout(small_dataset: Path) -> None:
    runs = read_dataset(small_dataset)
    series = runs_to_series(runs)
    for name, s in series.items():
        assert set(s) == {"v", "w", "v_ref", "w_ref", "seg"}
        assert len({len(a) for a in s.values()}) == 1
        np.testing.assert_array_equal(s["v_ref"], runs[name][0].command[:, 0])
        np.testing.assert_array_equal(s["w"], runs[name][0].state[:, 4])


def read_dataset_by_exact_stamp(path: Path, dt: float = 0.1) -> dict[str, list]:
    """The reader before stack recordings (states and commands matched by exact stamp), kept to hold the new
    pairing rule to it on dataset files."""
    from services.recording.mcap_io import read_messages

    keys = {"gpmppi/jackal/state": "state", "gpmppi/jackal/cmd": "cmd", "gpmppi/jackal/terrain/label": "label"}
    states, commands, labels = {}, {}, {}
    for key, _, msg in read_messages(path, keys=keys):
        stamp = msg.header.stamp_ns
        if keys[key] == "state":
            states[stamp] = msg.as_array()
        elif keys[key] == "cmd":
            commands[stamp] = [msg.v_ref, msg.omega_ref]
        else:
            labels[stamp] = msg.terrain
    stamps = sorted(set(states) & set(commands))
    runs: dict[str, list] = {}
    start = 0
    for i in range(1, len(stamps) + 1):
        if i < len(stamps):
            gap = (stamps[i] - stamps[i - 1]) / 1e9 > 1.5 * dt
            if not (gap or labels.get(stamps[i]) != labels.get(stamps[i - 1])):
                continue
        chunk = stamps[start:i]
        st = np.array([states[s] for s in chunk])
        runs.setdefault(labels[chunk[0]], []).append(
            ((np.array(chunk) - chunk[0]) / 1e9, st, np.array([commands[s] for s in chunk])))
        start = i
    return runs


def test_a_dataset_file_reads_bit_identical_to_exact_stamp_pairing(small_dataset: Path) -> None:
    new, old = read_dataset(small_dataset), read_dataset_by_exact_stamp(small_dataset)
    assert list(new) == list(old)
    for name in old:
        assert len(new[name]) == len(old[name])
        for run, (t, st, cmd) in zip(new[name], old[name], strict=True):
            assert run.time.tobytes() == t.tobytes()
            assert run.state.tobytes() == st.tobytes() and run.true_state.tobytes() == st.tobytes()
            assert run.command.tobytes() == cmd.tobytes()


def test_a_stack_recording_pairs_each_state_with_the_command_in_force(tmp_path: Path) -> None:
    """Odometry at 50 Hz with jitter, commands on their own later stamps, a lost stretch of commands, labels only
    now and then: 0.1 s ticks, each with the latest command at or before it, split where none is in force."""
    rng = np.random.default_rng(0)
    path = tmp_path / "stack.mcap"
    ms = 1_000_000
    with McapWriter(path) as writer:
        for k in range(200):  # 4 s of odometry at 50 Hz, a few ms of jitter
            stamp = 1_000 * ms + k * 20 * ms + int(rng.integers(0, 3 * ms))
            writer.write("gpmppi/jackal/state",
                         State(header=Header(stamp_ns=stamp), x=0.01 * k, y=0, theta=0, v=k, omega=0.0))
        for j in range(40):  # a command every 0.1 s, 30 ms after its tick; none from 1.8 s to 2.6 s
            if 18 <= j < 26:
                continue
            stamp = 1_000 * ms + j * 100 * ms + 30 * ms
            writer.write("gpmppi/jackal/cmd", Command(header=Header(stamp_ns=stamp), v_ref=float(j), omega_ref=0.0))
        for stamp, name in ((900 * ms, "gravel"), (3_500 * ms, "mud")):
            writer.write("gpmppi/jackal/terrain/label",
                         TerrainLabel(header=Header(stamp_ns=stamp), terrain=name))
    runs = read_dataset(path)
    assert set(runs) == {"gravel", "mud"}
    for rs in runs.values():
        for run in rs:
            gaps = np.diff(run.time)
            assert np.all((gaps > 0.075) & (gaps < 0.15)), gaps  # 50 Hz thinned to 0.1 s ticks
            tick_ms = 1_000 + 20 * run.state[:, 3]  # the state's odometry index gives its nominal stamp [ms]
            # the command in force: the latest stamped at or before the state (1000 + 100 j + 30 ms <= stamp)
            sent = np.array([j for j in range(40) if not 18 <= j < 26])
            latest = [sent[1_030 + 100 * sent <= t].max() for t in tick_ms]
            assert np.array_equal(run.command[:, 0], latest)
            assert np.all(tick_ms - (1_030 + 100 * run.command[:, 0]) <= 200)  # within the bound (2 dt)
    gravel, mud = runs["gravel"], runs["mud"]
    # the last command before the lost stretch (2.73 s) stays in force for 2 dt: the run (from 1.1 s) ends at 2.9 s; the
    # next command (3.63 s) comes after the label changed (3.5 s)
    assert len(gravel) == 1 and gravel[0].time[-1] == pytest.approx(1.8, abs=0.01) and gravel[0].command[-1, 0] == 17
    assert len(mud) == 1 and mud[0].command[0, 0] == 26.0 and mud[0].terrain == "mud"
    # the trainer reads the same ticks (one reader, tools/log_reader.py): its series are these runs in time order,
    # one segment each, numbered over all grounds
    from tools.train_data import read_log_series

    series = read_log_series(path, 0.1, None, None)
    for name, rs in runs.items():
        assert np.array_equal(series[name]["v_ref"], np.concatenate([r.command[:, 0] for r in rs]))
        assert np.array_equal(series[name]["yaw"], np.concatenate([r.state[:, 2] for r in rs]))
    assert list(series["gravel"]["seg"]) == [1] * len(gravel[0].time)
    assert set(series["mud"]["seg"]) == {2}


def test_a_log_of_another_robot_or_without_labels_is_refused_in_one_line(small_dataset: Path) -> None:
    """Both views of the reader refuse alike: the robot asked for and the keys the log holds, or what to name."""
    from tools.train_data import DataError, read_log_series

    for read in (lambda: read_dataset(small_dataset, robot="husky"),
                 lambda: read_log_series(small_dataset, 0.1, None, "husky")):
        with pytest.raises(DataError) as err:
            read()
        message = str(err.value)
        assert "\n" not in message and "'husky'" in message and "gpmppi/jackal/state" in message, message
        assert "--robot" in message
