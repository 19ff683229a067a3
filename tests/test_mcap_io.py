"""MCAP I/O: what McapWriter writes, the `mcap` reader reads back equal; crashes and rotation."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.records import Message as McapMessage
from mcap.stream_reader import breakup_chunk

from schemas import Command, Header, Plan, State, TerrainWeights, encode
from services.recording.mcap_io import read_messages, recording_files
from services.recording.mcap_writer import McapWriter

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


def _shuffled_recording(path: Path) -> None:
    """A recording of many small chunks whose log times run back across chunk boundaries, with ties in a chunk and
    across chunks (the recorder's log times are receive times: two topics' messages arrive out of their stamps'
    order): 400 states and commands on a 20 ms grid, each up to 60 ms off its place."""
    rng = np.random.default_rng(7)
    with McapWriter(path, chunk_size=1500) as writer:
        for i in range(400):
            t = 1_000_000_000 + 20_000_000 * (i // 2 + int(rng.integers(-3, 4)))
            if i % 2:
                writer.write("gpmppi/jackal/cmd", Command(header=Header(stamp_ns=t, seq=i), v_ref=1.0, omega_ref=0.0),
                             log_time_ns=t)
            else:
                writer.write("gpmppi/jackal/state", State(header=Header(stamp_ns=t, seq=i), x=0.0, y=0.0, theta=0.0,
                                                          v=1.0, omega=0.0), log_time_ns=t)


def test_the_reader_gives_mcaps_log_time_order_ties_in_file_order(tmp_path: Path) -> None:
    """`read_messages` sorts each chunk's messages by log time itself instead of mcap's heap
    (`iter_messages(log_time_order=True)`): the same messages in the same order, ties by their place in the file,
    all topics or some."""
    path = tmp_path / "shuffled.mcap"
    _shuffled_recording(path)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
        # the case the order is about: many chunks, a chunk starting before an earlier one ended
        assert len(chunks) > 10
        assert any(b.message_start_time < a.message_end_time for a, b in zip(chunks, chunks[1:], strict=False))
        in_file = [(c.topic, m.log_time, json.loads(m.data)["header"]["seq"])
                   for _, c, m in reader.iter_messages(log_time_order=False)]
        for topics in (None, ["gpmppi/jackal/cmd"]):
            heap = [(c.topic, m.log_time, json.loads(m.data)["header"]["seq"])
                    for _, c, m in reader.iter_messages(topics=topics, log_time_order=True)]
            ours = [(k, t, m.header.seq) for k, t, m in read_messages(path, keys=topics)]
            assert ours == heap
    ours_all = [(k, t, m.header.seq) for k, t, m in read_messages(path)]
    assert len(in_file) == 400 and sorted(ours_all) == sorted(in_file)
    assert ours_all != in_file  # the file is out of order: the sort is what is checked
    # log times that tie across chunks: their order is the file's, whatever the chunks' time ranges
    chunk_of: dict[int, int] = {}
    with open(path, "rb") as f:
        for n, index in enumerate(chunks):
            f.seek(index.chunk_start_offset + 1 + 8)
            for record in breakup_chunk(Chunk.read(ReadDataStream(f))):
                if isinstance(record, McapMessage):
                    chunk_of[json.loads(record.data)["header"]["seq"]] = n
    assert len(chunk_of) == 400
    assert any(a[1] == b[1] and chunk_of[a[2]] != chunk_of[b[2]] for a, b in zip(ours_all, ours_all[1:], strict=False))
    position = {seq: n for n, (_, _, seq) in enumerate(in_file)}
    assert all((a[1], position[a[2]]) < (b[1], position[b[2]]) for a, b in zip(ours_all, ours_all[1:], strict=False))


def test_crash_loses_at_most_the_open_chunk(tmp_path: Path) -> None:
    """A writer killed without close(): every chunk already flushed is recovered."""
    path = tmp_path / "crash.mcap"
    code = f"""
import os
from schemas import State
from services.recording.mcap_writer import McapWriter
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
    # a part ends after the chunk that crosses max_bytes; it holds the channel's JSON Schema at its start and again
    # in its summary
    schema = len(json.dumps(Command.model_json_schema()))
    assert all(p.stat().st_size < 5000 + 1000 + 2 * schema + 500 for p in parts), [p.stat().st_size for p in parts]
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


# ---- the recorder's path: validation, quarantine, record fields, metadata, write errors ----------------
HOSTILE: list[bytes] = [
    b"",
    b"{",
    b"null",
    b'{"v_ref": NaN, "omega_ref": 0}',
    b"[" * 5000 + b"]" * 5000,
    b"[" + b"1.0," * 1_300_000 + b"1.0]",  # ~5 MB: over the payload limit
    b'{"v_ref": "1.0", "omega_ref": 0}',  # a number as a string: lenient parsing takes it, the JSON Schema does not
    b'{"header": {"seq": "3"}, "v_ref": 1, "omega_ref": 0}',
    b"\xff\xfe not utf-8",
]


def _schema_validators(path: Path) -> dict[str, object]:
    import jsonschema

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return {
        c.topic: jsonschema.Draft202012Validator(json.loads(summary.schemas[c.schema_id].data))
        for c in summary.channels.values()
        if c.schema_id
    }


def test_record_quarantines_what_breaks_the_schema(tmp_path: Path) -> None:
    path = tmp_path / "q.mcap"
    key = "gpmppi/r1/cmd"
    with McapWriter(path, chunk_size=50_000) as writer:
        for i in range(20):
            good = Command(header=Header(stamp_ns=5_000 + i, seq=100 + i), v_ref=0.1 * i, omega_ref=0.0)
            assert writer.record(key, encode(good), log_time_ns=1_000 + i)
            for payload in HOSTILE:
                assert not writer.record(key, payload, log_time_ns=1_000 + i)
        assert writer.record("gpmppi/r1/custom/thing", b'{"a": [1, 2]}', log_time_ns=2_000)  # no model: JSON
        assert not writer.record("gpmppi/r1/custom/thing", b"{nope", log_time_ns=2_001)
        assert not writer.record("gpmppi/r1/custom/thing", b"NaN", log_time_ns=2_002)
        assert writer.quarantined == 20 * len(HOSTILE) + 2
    validators = _schema_validators(path)
    assert set(validators) == {key}
    by_topic: dict[str, list] = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            by_topic.setdefault(channel.topic, []).append((schema, channel, message))
    # the schema'd channel: only valid messages, each validating; publish time = header stamp, sequence = seq
    good = by_topic[key]
    assert len(good) == 20
    for i, (_, _, message) in enumerate(good):
        validators[key].validate(json.loads(message.data))  # type: ignore[attr-defined]
        assert (message.log_time, message.publish_time, message.sequence) == (1_000 + i, 5_000 + i, 100 + i)
    # the quarantine channel: schema-less, raw bytes exactly as received, in order
    rejected = by_topic[key + "/_rejected"]
    assert all(s is None and c.schema_id == 0 and c.message_encoding == "application/octet-stream"
               for s, c, _ in rejected)
    assert [m.data for _, _, m in rejected] == HOSTILE * 20
    # a key with no model: schema-less JSON on its own key; what is not JSON is quarantined
    (custom,) = by_topic["gpmppi/r1/custom/thing"]
    assert custom[1].message_encoding == "json" and custom[1].schema_id == 0 and custom[2].data == b'{"a": [1, 2]}'
    assert [m.data for _, _, m in by_topic["gpmppi/r1/custom/thing/_rejected"]] == [b"{nope", b"NaN"]
    # our reader yields the valid messages only, without complaint about the quarantine
    assert [m.header.seq for _, _, m in read_messages(path)] == list(range(100, 120))


def test_metadata_and_attachments_round_trip_and_rotated_parts_carry_the_metadata(tmp_path: Path) -> None:
    path = tmp_path / "meta.mcap"
    run = {"version": "0.1.0", "commit": "abc", "host": "h", "robot": "r1", "started_ns": "12", "launch_file": ""}
    model = bytes(range(256)) * 400  # 100 kB: bigger than a part, so rotation must not count it
    with McapWriter(path, chunk_size=1000, max_bytes=4000) as writer:
        writer.add_metadata("gpmppi.run", run)
        writer.add_attachment("model/m.npz", model, "application/octet-stream")
        for i in range(200):
            writer.write("gpmppi/r1/cmd", Command(header=Header(seq=i), v_ref=0.5, omega_ref=0.0), log_time_ns=i)
    parts = recording_files(path)
    assert 3 <= len(parts) < 40
    for index, part in enumerate(parts):
        with open(part, "rb") as f:
            reader = make_reader(f)
            assert [(m.name, m.metadata) for m in reader.iter_metadata()] == [("gpmppi.run", run)]
            attachments = [(a.name, a.media_type, a.data) for a in reader.iter_attachments()]
        assert attachments == ([("model/m.npz", "application/octet-stream", model)] if index == 0 else [])
    assert [m.header.seq for _, _, m in read_messages(path)] == list(range(200))


def test_a_write_error_stops_the_writer_and_leaves_a_readable_file(tmp_path: Path) -> None:
    """A file-size limit (what a full disk does too): one OSError, then `failed`; the file reads back."""
    path = tmp_path / "full.mcap"
    code = f"""
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (40_000, 40_000))
from schemas import Command, Header, encode
from services.recording.mcap_writer import McapWriter
w = McapWriter({str(path)!r}, chunk_size=2000, compression="none")
n = 0
try:
    for i in range(100_000):
        w.record("gpmppi/r1/cmd", encode(Command(header=Header(seq=i), v_ref=1.0, omega_ref=0.0)), i + 1)
        n += 1
except OSError as exc:
    print("ERR", exc.errno, w.failed, n)
try:
    w.record("gpmppi/r1/cmd", b"{{}}", 1)
except RuntimeError as exc:
    print("AFTER", exc)
w.close()
"""
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, timeout=60, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    err = next(line for line in out.stdout.splitlines() if line.startswith("ERR"))
    assert "File too large" in err and "EFBIG" in err
    assert "stopped after a write error" in out.stdout
    assert path.stat().st_size <= 40_000
    seqs = [m.header.seq for _, _, m in read_messages(path)]
    accepted = int(err.split()[-1])
    assert seqs == list(range(len(seqs))) and accepted - 40 <= len(seqs) <= accepted
