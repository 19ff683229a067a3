"""MCAP recordings of gpmppi messages: how one is laid out (its channels' names and schemas, its rotated parts) and
reading it back. Writing is `services.recording.mcap_writer.McapWriter`.

Messages are stored as JSON (`message_encoding="json"`) with the pydantic model's JSON Schema
(`schema encoding="jsonschema"`), so Foxglove and the `mcap` CLI open the files without any
plugin. A file that was never closed (a crash) is still read back by `read_messages`: every complete
chunk is recovered by a linear scan. A rotated recording continues in `<stem>_001.mcap`, `<stem>_002.mcap`, ... ;
`recording_files(path)` lists the parts of a recording in order. What failed its key's model is on the schema-less
quarantine channel `<key>/_rejected`, which reading skips.
"""

from __future__ import annotations

import bisect
import io
import logging
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO

from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, ChunkIndex
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.summary import Summary

from schemas import DecodeError, Message, decode, model_for_key
from schemas.messages import MODELS

log = logging.getLogger(__name__)

PROFILE = ""  # no ROS profile: plain JSON messages
LIBRARY = "gpmppi"
SCHEMA_PREFIX = "gpmppi."
# the Foxglove scene (services.view.foxglove_scene): channels in Foxglove's own schemas, written beside the messages
# for Foxglove's 3D panel; they are views, not gpmppi messages, and reading a recording leaves them out
FOXGLOVE_SCHEMA_PREFIX = "foxglove."
REJECTED_SUFFIX = "/_rejected"  # quarantine: payloads that break their key's model, raw and schema-less
RAW_ENCODING = "application/octet-stream"


def rejected_topic(key: str) -> str:
    """The quarantine channel of a key: `<key>/_rejected`."""
    return key + REJECTED_SUFFIX


def schema_name(model: type[Message]) -> str:
    return SCHEMA_PREFIX + model.__name__


def rotated_path(path: Path, index: int) -> Path:
    return path if index == 0 else path.with_name(f"{path.stem}_{index:03d}{path.suffix}")


def recording_files(path: str | Path) -> list[Path]:
    """The existing parts of a (possibly rotated) recording, in order: path, <stem>_001, ..."""
    path = Path(path)
    parts: list[Path] = []
    index = 0
    while rotated_path(path, index).is_file():
        parts.append(rotated_path(path, index))
        index += 1
    return parts


# ---- reading ----------------------------------------------------------------------------------
def _in_log_time_order(
    stream: IO[bytes], summary: Summary, keys: set[str] | None
) -> Iterator[tuple[str, str | None, McapMessage]]:
    """(topic, schema name, record) of an indexed file in log-time order, ties in file order: the order of mcap's
    `iter_messages(log_time_order=True)` (its heap orders by log time, then chunk offset, then place in the chunk).

    Why not that heap: it compares Python objects at every push and pop, about half of what reading a recording
    cost (`read_log_runs`). Here each chunk's messages are read in file order and sorted, stably, by log time with
    what earlier chunks left; what is at or before the earliest start of the chunks still to read cannot be
    preceded by any of theirs (their ties come later in the file), so it goes out. Chunks written in time order
    (the writer's) leave nothing pending, so memory stays a chunk or two, as with the heap.
    """
    channels = summary.channels
    # no keys (None, or none given) reads every topic, as mcap's `iter_messages(topics=None)` did here
    wanted = None if not keys else {cid for cid, c in channels.items() if c.topic in keys}
    chunks = sorted(
        (c for c in summary.chunk_indexes if _may_hold(c, wanted)), key=lambda c: c.chunk_start_offset
    )
    # the earliest log time any chunk from the k-th on may hold
    later_start = [0] * len(chunks)
    earliest: int | None = None
    for k in range(len(chunks) - 1, -1, -1):
        start = chunks[k].message_start_time
        earliest = start if earliest is None else min(earliest, start)
        later_start[k] = earliest
    schema_names: dict[int, str | None] = {}  # a channel's, at its first message (a missing one fails as in mcap's)
    pending: list[tuple[str, str | None, McapMessage]] = []
    for k, index in enumerate(chunks):
        stream.seek(index.chunk_start_offset + 1 + 8, io.SEEK_SET)  # past the record's opcode and length
        for record in breakup_chunk(Chunk.read(ReadDataStream(stream))):
            if isinstance(record, McapMessage) and (wanted is None or record.channel_id in wanted):
                cid = record.channel_id
                channel = channels[cid]
                if cid not in schema_names:
                    schema_names[cid] = summary.schemas[channel.schema_id].name if channel.schema_id else None
                pending.append((channel.topic, schema_names[cid], record))
        pending.sort(key=_log_time)  # stable: ties keep file order, the earlier chunks' first
        if k + 1 == len(chunks):
            yield from pending
            return
        ready = bisect.bisect_right(pending, later_start[k + 1], key=_log_time)
        yield from pending[:ready]
        del pending[:ready]


def _log_time(item: tuple[str, str | None, McapMessage]) -> int:
    return item[2].log_time


def _may_hold(chunk: ChunkIndex, wanted: set[int] | None) -> bool:
    """Whether `chunk` may hold a message on the `wanted` channels (all where None): its message index says which
    channels it holds, where the file has one."""
    return wanted is None or not chunk.message_index_offsets or not wanted.isdisjoint(chunk.message_index_offsets)


def _iter_raw(path: Path, keys: set[str] | None) -> Iterator[tuple[str, str | None, McapMessage]]:
    """(topic, schema name, record) in log-time order; falls back to a linear scan for unfinished files."""
    with open(path, "rb") as stream:
        try:
            reader = make_reader(stream)
            summary = reader.get_summary()
        except Exception as exc:  # noqa: BLE001 - any failure here means no usable footer/summary
            log.warning("%s has no readable summary (%s); recovering complete chunks by a linear scan", path, exc)
            summary = None
        if summary is not None and summary.chunk_indexes:
            yield from _in_log_time_order(stream, summary, keys)
            return
        if summary is not None:  # no chunks: mcap's reader scans the file and sorts it
            for schema, channel, message in reader.iter_messages(topics=sorted(keys) if keys else None):
                yield channel.topic, schema.name if schema else None, message
            return
        stream.seek(0)
        channels: dict[int, tuple[str, int]] = {}
        schemas: dict[int, str] = {}
        records = StreamReader(stream, skip_magic=False).records
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except Exception as exc:  # noqa: BLE001 - a truncated tail ends the scan
                log.warning("%s ends in an incomplete record (%s): stopped there", path, type(exc).__name__)
                return
            kind = type(record).__name__
            if kind == "Schema":
                schemas[record.id] = record.name
            elif kind == "Channel":
                channels[record.id] = (record.topic, record.schema_id)
            elif isinstance(record, McapMessage) and record.channel_id in channels:
                topic, schema_id = channels[record.channel_id]
                if keys is None or topic in keys:
                    yield topic, schemas.get(schema_id), record


def read_messages(
    path: str | Path, keys: Iterable[str] | None = None, skipped: dict[str, tuple[int, str]] | None = None
) -> Iterator[tuple[str, int, Message]]:
    """(key, log_time_ns, decoded message) for every message in the recording at `path`.

    `keys` limits the topics (exact keys). Quarantine channels (`<key>/_rejected`) are not messages and are
    skipped; messages on keys with no registered model, or that do not decode (a foreign schema, CDR, ...),
    are skipped with one warning per topic that says how many, and counted in `skipped` if given
    (topic -> (messages skipped, the first reason)). Rotated parts (`<stem>_001.mcap`, ...) are read after `path`.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no MCAP recording at {path}")
    wanted = set(keys) if keys is not None else None
    by_name = {schema_name(m): m for m in MODELS.values()}
    for part in recording_files(path) or [path]:
        part_skipped: dict[str, tuple[int, str]] = {}
        for topic, name, record in _iter_raw(part, wanted):
            if topic.endswith(REJECTED_SUFFIX) or (name or "").startswith(FOXGLOVE_SCHEMA_PREFIX):
                continue  # quarantined payloads and the Foxglove scene are not gpmppi messages
            model = by_name.get(name) if name else None
            try:
                model = model or model_for_key(topic)
                yield topic, record.log_time, decode(model, record.data)
            except (KeyError, DecodeError) as exc:
                count, first = part_skipped.get(topic, (0, str(exc)))
                part_skipped[topic] = (count + 1, first)
        for topic, (count, first) in part_skipped.items():
            log.warning("%s: skipped %d message(s) on %s that are not gpmppi messages: %s", part, count, topic, first)
            if skipped is not None:
                total, reason = skipped.get(topic, (0, first))
                skipped[topic] = (total + count, reason)
