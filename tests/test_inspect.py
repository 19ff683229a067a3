"""`gpmppi inspect`: complete, truncated, rotated, still-being-written, foreign and broken files; --json and
--recover. Real MCAP files, written by McapWriter or the mcap library, read back by the mcap reader."""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import typer
from mcap.reader import make_reader
from mcap.writer import Writer
from typer.testing import CliRunner

from schemas import Command, Header, State
from services.recording.mcap_inspect import inspect_recording, recover
from services.recording.mcap_io import read_messages, recording_files
from services.recording.mcap_writer import McapWriter
from tools import inspect_cmd

REPO = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000_000


def _app() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def main() -> None:  # a group, so `inspect` stays a subcommand as in `gpmppi`
        pass

    inspect_cmd.register(app)
    return app


def _inspect(*args: str) -> tuple[int, str, str]:
    result = CliRunner().invoke(_app(), ["inspect", *args])
    return result.exit_code, result.stdout, result.stderr


def _write_run(path: Path, **writer_options: object) -> None:
    """cmd at 10 Hz for 3 s, a 2 s silence, 1 s more; state at 20 Hz for 6 s; metadata; an attachment."""
    with McapWriter(path, **writer_options) as w:  # type: ignore[arg-type]
        w.add_metadata("gpmppi.run", {"version": "0.1.0", "robot": "r1"})
        w.add_attachment("launch.yaml", b"robot: r1\n", "application/yaml")
        cmd_times = [T0 + i * 100_000_000 for i in range(30)]
        cmd_times += [T0 + 5_000_000_000 + i * 100_000_000 for i in range(10)]
        events = [(t, "cmd", i) for i, t in enumerate(cmd_times)]
        events += [(T0 + i * 50_000_000, "state", i) for i in range(120)]
        for t, kind, i in sorted(events):
            if kind == "cmd":
                w.write("gpmppi/r1/cmd", Command(header=Header(stamp_ns=t, seq=i), v_ref=0.1, omega_ref=0.0), t)
            else:
                msg = State(header=Header(stamp_ns=t, seq=i), x=float(i), y=0.0, theta=0.0, v=1.0, omega=0.0)
                w.write("gpmppi/r1/state", msg, t)


def test_a_complete_file(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    _write_run(path)
    code, out, _ = _inspect(str(path), "--json")
    assert code == 0
    data = json.loads(out)
    assert data["messages"] == 160 and data["truncated"] is False and data["recovered_messages"] == 0
    assert data["duration_s"] == pytest.approx(5.95)
    channels = {c["topic"]: c for c in data["channels"]}
    cmd, state = channels["gpmppi/r1/cmd"], channels["gpmppi/r1/state"]
    assert (cmd["schema"], cmd["encoding"], cmd["count"]) == ("gpmppi.Command", "json", 40)
    assert cmd["rate_hz"] == pytest.approx(39 / 5.9)
    assert cmd["max_gap_s"] == pytest.approx(2.1) and cmd["max_gap_at_s"] == pytest.approx(2.9)
    assert (cmd["first_s"], cmd["last_s"]) == (0.0, pytest.approx(5.9))
    assert state["count"] == 120 and state["rate_hz"] == pytest.approx(20.0)
    assert state["max_gap_s"] == pytest.approx(0.05)
    assert data["metadata"] == {"gpmppi.run": {"version": "0.1.0", "robot": "r1"}}
    attachment = {"name": "launch.yaml", "media_type": "application/yaml", "bytes": 10, "file": "run.mcap"}
    assert data["attachments"] == [attachment]
    code, text, _ = _inspect(str(path))
    assert code == 0
    assert "complete, 160 messages" in text and "gpmppi.run: version=0.1.0 robot=r1" in text and "launch.yaml" in text
    assert any(line.split()[:3] == ["gpmppi/r1/cmd", "gpmppi.Command", "40"] for line in text.splitlines())


def test_a_truncated_file_reads_to_its_last_complete_chunk_and_recovers(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    _write_run(full, chunk_size=1500)
    data = full.read_bytes()
    counts = []
    for fraction in (0.3, 0.55, 0.97):
        cut = tmp_path / f"cut{fraction}.mcap"
        cut.write_bytes(data[: int(len(data) * fraction)])
        report = inspect_recording(cut)
        assert report.truncated and report.recovered_messages == report.messages
        counts.append(report.messages)
        # what is recovered is exactly the first messages of each channel, in order
        seqs = [m.header.seq for k, _, m in read_messages(cut) if k == "gpmppi/r1/state"]
        assert seqs == list(range(len(seqs)))
        code, text, _ = _inspect(str(cut))
        assert code == 0 and "TRUNCATED" in text and f"{report.messages} messages recovered" in text
    # more of the file, more messages; at 97 % only the summary is cut, every chunk is there
    assert 0 < counts[0] < counts[1] < counts[2] == 160
    cut = tmp_path / "cut0.55.mcap"
    out = tmp_path / "recovered.mcap"
    code, text, _ = _inspect(str(cut), "--recover", str(out), "--json")
    assert code == 0 and json.loads(text)["recovered_written"] == counts[1]
    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == counts[1]
        assert [m.name for m in reader.iter_metadata()] == ["gpmppi.run"]
        assert [a.name for a in reader.iter_attachments()] == ["launch.yaml"]
    assert not inspect_recording(out).truncated
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []
    with pytest.raises(Exception, match="overwrite"):
        recover(cut, cut)


def test_a_rotated_set(tmp_path: Path) -> None:
    path = tmp_path / "rot.mcap"
    _write_run(path, chunk_size=1000, max_bytes=3000)
    parts = recording_files(path)
    assert len(parts) >= 3
    code, out, _ = _inspect(str(path), "--json")
    assert code == 0
    data = json.loads(out)
    assert [Path(f["path"]).name for f in data["files"]] == [p.name for p in parts]
    assert data["messages"] == 160 and not data["truncated"]
    assert {c["topic"]: c["count"] for c in data["channels"]} == {"gpmppi/r1/cmd": 40, "gpmppi/r1/state": 120}
    assert data["metadata"] == {"gpmppi.run": {"version": "0.1.0", "robot": "r1"}}  # repeated per part, shown once
    # a later part that is not MCAP: the rest is still reported, the exit code says partial
    parts[1].write_bytes(b"garbage garbage")
    code, text, _ = _inspect(str(path))
    assert code == 1 and "UNREADABLE" in text and parts[1].name in text and "not an MCAP file" in text


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        (None, "no such file"),
        (b"", "empty file (0 bytes)"),
        (b"PK\x03\x04 this is a zip", "not an MCAP file"),
        (b"\x89MC", "too short to be an MCAP file"),
    ],
)
def test_bad_files_give_one_clear_line_and_exit_2(tmp_path: Path, content: bytes | None, expected: str) -> None:
    path = tmp_path / "bad.mcap"
    if content is not None:
        path.write_bytes(content)
    code, out, err = _inspect(str(path))
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and expected in lines[0] and str(path) in lines[0], err
    code, _, err = _inspect(str(path), "--recover", str(tmp_path / "out.mcap"))
    assert code == 2 and expected in err and not (tmp_path / "out.mcap").exists()


def test_a_file_still_being_written_reads_as_truncated_so_far(tmp_path: Path) -> None:
    path = tmp_path / "live.mcap"
    writer = McapWriter(path, chunk_size=10_000_000)
    try:
        for i in range(50):
            writer.write("gpmppi/r1/cmd", Command(header=Header(seq=i), v_ref=0.0, omega_ref=0.0), T0 + i)
        assert inspect_recording(path).messages == 0  # nothing flushed yet: a header only
        writer.flush()
        first = inspect_recording(path)
        assert first.truncated and first.messages == 50
        for i in range(50, 80):
            writer.write("gpmppi/r1/cmd", Command(header=Header(seq=i), v_ref=0.0, omega_ref=0.0), T0 + i)
        writer.flush()
        assert inspect_recording(path).messages == 80
    finally:
        writer.close()
    done = inspect_recording(path)
    assert not done.truncated and done.messages == 80


def test_foreign_schemas_and_non_json_channels(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """inspect describes any MCAP (it decodes nothing); the gpmppi reader skips what it cannot decode, once per
    topic, with a warning that names it."""
    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="other")
        ros = w.register_schema("geometry_msgs/msg/Twist", "ros2msg", b"geometry_msgs/Vector3 linear\n")
        proto = w.register_schema("foo.Bar", "protobuf", b"\x0a\x00")
        channels = [
            w.register_channel("/cmd_vel", "cdr", ros),
            w.register_channel("/bar", "protobuf", proto),
            w.register_channel("/blob", "application/octet-stream", 0),
            w.register_channel("gpmppi/r1/cmd", "cdr", ros),  # a gpmppi key carrying something else
        ]
        for i in range(10):
            for c in channels:
                w.add_message(c, log_time=T0 + i * 10**8, data=b"\x00\x01\x02\x03", publish_time=T0 + i * 10**8)
        w.finish()
    code, out, _ = _inspect(str(path), "--json")
    assert code == 0
    data = json.loads(out)
    got = {c["topic"]: (c["schema"], c["encoding"], c["count"]) for c in data["channels"]}
    assert got == {
        "/cmd_vel": ("geometry_msgs/msg/Twist", "cdr", 10),
        "/bar": ("foo.Bar", "protobuf", 10),
        "/blob": ("", "application/octet-stream", 10),
        "gpmppi/r1/cmd": ("geometry_msgs/msg/Twist", "cdr", 10),
    }
    assert data["files"][0]["library"] == "other" and data["messages"] == 40
    with caplog.at_level(logging.WARNING, logger="services.recording.mcap_io"):
        assert list(read_messages(path)) == []
    warnings = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
    assert len(warnings) == 4 and any("skipped 10 message(s) on gpmppi/r1/cmd" in w for w in warnings)


def test_the_gpmppi_command_registers_inspect(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    _write_run(path)
    shutil.copy(path, tmp_path / "copy.mcap")
    out = subprocess.run(
        [sys.executable, "-m", "tools.cli", "inspect", str(tmp_path / "copy.mcap"), "--json"],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["messages"] == 160


def test_a_corrupt_chunk_gives_partial_results_and_says_where(tmp_path: Path) -> None:
    path = tmp_path / "corrupt.mcap"
    _write_run(path, chunk_size=1500, compression="none")
    data = bytearray(path.read_bytes())
    at = data.index(b'"x":60.0')  # inside a chunk in the middle of the file
    data[at + 5] = ord("9")  # one flipped byte: the chunk's CRC no longer matches
    path.write_bytes(bytes(data))
    code, out, _ = _inspect(str(path), "--json")
    assert code == 1
    report = json.loads(out)
    assert 0 < report["messages"] < 160 and report["truncated"]
    (error,) = report["errors"]
    assert "CRC" in error and "unreadable after byte" in error


def test_a_file_cut_inside_a_large_attachment_is_truncated_not_corrupt(tmp_path: Path) -> None:
    """The recorder attaches the GP model (MBs) early: a kill while it is written cuts a record longer than
    what is left of the file; that is a truncation, with the messages before it recovered."""
    path = tmp_path / "att.mcap"
    with McapWriter(path, chunk_size=500) as w:
        for i in range(20):
            w.write("gpmppi/r1/cmd", Command(header=Header(seq=i), v_ref=0.0, omega_ref=0.0), T0 + i)
        w.flush()
        w.add_attachment("model/m.npz", bytes(200_000), "application/octet-stream")
        for i in range(20, 40):
            w.write("gpmppi/r1/cmd", Command(header=Header(seq=i), v_ref=0.0, omega_ref=0.0), T0 + i)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    code, out, _ = _inspect(str(cut), "--json")
    report = json.loads(out)
    assert code == 0 and report["truncated"] and report["messages"] == 20 and report["errors"] == []
