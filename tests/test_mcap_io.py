"""MCAP I/O: what McapWriter writes, the `mcap` reader reads back equal; crashes and rotation."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader

from schemas import Command, Header, Plan, State, TerrainWeights, encode
from services.mcap_io import McapWriter, read_messages, recording_files

REPO = Path(__file__).resolve().parents[1]


def _messages() -> list[tuple[str, int, object]]:
    out: list[tuple[str, int, object]] = []
    for i in range(50):
        t = 1_000_000_000 + i * 100_000_000
        out.append(
            (
                "gpmppi/jackal/state",
                t,
                State(
                    header=Header(stamp_ns=t, seq=i),
                    x=i * 0.1,
                    y=-1.5,
                    theta=0.2,
                    v=1.0,
                    omega=-0.3,
                    covariance=[0.01 * k for k in range(25)],
                ),
            )
        )
        out.append(("gpmppi/jackal/cmd", t, Command(header=Header(stamp_ns=t, seq=i), v_ref=1.2, omega_ref=0.01 * i)))
    out.append(("gpmppi/jackal/terrain/weights", t, TerrainWeights(names=["a", "b"], weights=[0.25, 0.75])))
    cmd = Command(v_ref=1.0, omega_ref=0.0)
    out.append(("gpmppi/jackal/plan", t, Plan(command=cmd, controls=[[1.0, 0.0]], states=[[0, 0, 0, 0, 0]] * 2)))
    return out


def test_write_then_mcap_reader_reads_equal(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "run.mcap"
    written = _messages()
    with McapWriter(path) as writer:
        for key, t, msg in written:
            writer.write(key, msg, log_time_ns=t)
    # independent check with the mcap library's own reader: JSON + JSON Schema, topics = keys
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == len(written)
        raw = list(reader.iter_messages(log_time_order=False))
    assert len(raw) == len(written)
    for (schema, channel, message), (key, t, msg) in zip(raw, written, strict=True):
        assert channel.topic == key and channel.message_encoding == "json"
        assert schema is not None and schema.encoding == "jsonschema"
        assert json.loads(schema.data)["title"] == type(msg).__name__
        assert message.log_time == t
        assert json.loads(message.data) == json.loads(encode(msg))
    # our reader decodes back to equal pydantic models
    back = list(read_messages(path))
    assert sorted(back, key=lambda r: (r[1], r[0])) == sorted(written, key=lambda r: (r[1], r[0]))
    only_cmd = list(read_messages(path, keys=["gpmppi/jackal/cmd"]))
    assert len(only_cmd) == 50 and all(isinstance(m, Command) for _, _, m in only_cmd)


def test_crash_loses_at_most_the_open_chunk(tmp_path: Path) -> None:
    """A writer killed without close(): every chunk already flushed is recovered."""
    path = tmp_path / "crash.mcap"
    code = f"""
import os
from schemas import State
from services.mcap_io import McapWriter
w = McapWriter({str(path)!r}, chunk_size=2000, flush_interval_s=1000.0)
for i in range(200):
    w.write("gpmppi/jackal/state", State(x=float(i), y=0.0, theta=0.0, v=1.0, omega=0.0), log_time_ns=i + 1)
os._exit(0)
"""
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO, timeout=60)
    back = list(read_messages(path))
    # 200 messages of ~120 bytes; chunks flush every 2000 bytes, so only the last partial chunk may be lost
    assert 200 - 20 <= len(back) < 200
    assert [m.x for _, _, m in back] == [float(i) for i in range(len(back))]


def test_rotation_by_size_keeps_every_message(tmp_path: Path) -> None:
    path = tmp_path / "rot.mcap"
    with McapWriter(path, chunk_size=1000, max_bytes=5000) as writer:
        for i in range(300):
            writer.write("gpmppi/jackal/cmd", Command(header=Header(seq=i), v_ref=0.5, omega_ref=0.0), log_time_ns=i)
    parts = recording_files(path)
    assert len(parts) >= 3 and parts == writer.files
    assert all(p.stat().st_size < 5000 + 2000 for p in parts)
    seqs = [m.header.seq for _, _, m in read_messages(path)]
    assert seqs == list(range(300))


def test_writer_rejects_bad_options_and_closed_use(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="compression"):
        McapWriter(tmp_path / "x.mcap", compression="gzip")
    writer = McapWriter(tmp_path / "y.mcap")
    writer.close()
    writer.close()
    with pytest.raises(RuntimeError, match="closed"):
        writer.write("gpmppi/jackal/cmd", Command(v_ref=0.0, omega_ref=0.0))
    with pytest.raises(FileNotFoundError):
        list(read_messages(tmp_path / "missing.mcap"))
