"""What is in an MCAP recording, read straight from its records: per channel (topic, schema, count, rate,
first and last time, largest gap), the whole recording (duration, messages, metadata, attachments), rotated
parts, and whether each file is complete. The logic behind `gpmppi inspect`; it needs no Zenoh.

Every file is read by a linear scan of its records, so a file without a summary (the recorder was killed, or
is still writing) reads as far as its last complete chunk: it is reported as truncated, with the number of
messages recovered. `recover` writes those messages (and the metadata and attachments) to a complete file.
Any MCAP file is described, whatever its schemas and encodings: nothing here decodes a message.
"""

from __future__ import annotations

import os
import struct
import tempfile
from array import array
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
from mcap.records import Attachment, Channel, Footer, Header, McapRecord, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from services.recording.mcap_io import recording_files

MAGIC = b"\x89MCAP0\r\n"


class InspectError(Exception):
    """Nothing could be read: the path is missing, empty, or not an MCAP file."""


@dataclass
class ChannelStats:
    topic: str
    schema: str  # schema name, "" when the channel has none
    encoding: str  # message encoding
    times: array = field(default_factory=lambda: array("q"))  # log times [ns]

    def summary(self, t0: int) -> dict[str, Any]:
        times = sorted(self.times)
        n = len(times)
        first, last = (times[0], times[-1]) if n else (0, 0)
        span_s = (last - first) / 1e9
        gap, at = 0, first
        for a, b in zip(times, times[1:], strict=False):
            if b - a > gap:
                gap, at = b - a, a
        return {
            "topic": self.topic,
            "schema": self.schema,
            "encoding": self.encoding,
            "count": n,
            "rate_hz": (n - 1) / span_s if n > 1 and span_s > 0 else 0.0,
            "first_ns": first,
            "last_ns": last,
            "first_s": (first - t0) / 1e9 if n else 0.0,
            "last_s": (last - t0) / 1e9 if n else 0.0,
            "max_gap_s": gap / 1e9,
            "max_gap_at_s": (at - t0) / 1e9 if n > 1 else 0.0,
        }


@dataclass
class FileReport:
    path: Path
    bytes: int = 0
    messages: int = 0
    complete: bool = False  # the footer (after the summary) was reached
    library: str = ""
    error: str = ""  # why the scan stopped early (a truncated tail is not an error: see `truncated`)

    @property
    def truncated(self) -> bool:
        return not self.complete

    def to_json(self) -> dict[str, Any]:
        return {
            "path": str(self.path),
            "bytes": self.bytes,
            "messages": self.messages,
            "truncated": self.truncated,
            "library": self.library,
            "error": self.error,
        }


@dataclass
class Report:
    path: Path
    files: list[FileReport] = field(default_factory=list)
    channels: dict[tuple[str, str, str], ChannelStats] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: list[dict[str, Any]] = field(default_factory=list)

    @property
    def messages(self) -> int:
        return sum(f.messages for f in self.files)

    @property
    def truncated(self) -> bool:
        return any(f.truncated for f in self.files)

    @property
    def recovered_messages(self) -> int:
        """Messages read from files without a summary."""
        return sum(f.messages for f in self.files if f.truncated)

    def span_ns(self) -> tuple[int, int]:
        firsts = [min(c.times) for c in self.channels.values() if c.times]
        lasts = [max(c.times) for c in self.channels.values() if c.times]
        return (min(firsts), max(lasts)) if firsts else (0, 0)

    def to_json(self) -> dict[str, Any]:
        start, end = self.span_ns()
        return {
            "path": str(self.path),
            "files": [f.to_json() for f in self.files],
            "messages": self.messages,
            "duration_s": (end - start) / 1e9,
            "start_ns": start,
            "end_ns": end,
            "truncated": self.truncated,
            "recovered_messages": self.recovered_messages,
            "channels": [c.summary(start) for c in sorted(self.channels.values(), key=lambda c: c.topic)],
            "metadata": self.metadata,
            "attachments": self.attachments,
            "errors": [f"{f.path}: {f.error}" for f in self.files if f.error],
        }


def _check_file(path: Path) -> None:
    """Raise InspectError for a file that holds no MCAP at all."""
    if not path.exists():
        raise InspectError(f"{path}: no such file")
    if not path.is_file():
        raise InspectError(f"{path}: not a file")
    size = path.stat().st_size
    if size == 0:
        raise InspectError(f"{path}: empty file (0 bytes): the recorder wrote nothing (stopped at once, or no space)")
    with open(path, "rb") as f:
        head = f.read(len(MAGIC))
    if head != MAGIC[: len(head)] or len(head) < len(MAGIC):
        what = "too short to be" if head == MAGIC[: len(head)] else "not"
        raise InspectError(f"{path}: {what} an MCAP file (it starts with {head[:8]!r}; MCAP starts with {MAGIC!r})")


def scan_file(path: Path, on_record: Callable[[McapRecord], None]) -> FileReport:
    """Every record of one file, in file order, to `on_record`; stops cleanly at a truncated or corrupt tail."""
    _check_file(path)
    report = FileReport(path=path, bytes=path.stat().st_size)
    with open(path, "rb") as stream:
        records = StreamReader(stream, validate_crcs=True, record_size_limit=report.bytes).records
        while True:
            try:
                record = next(records)
            except StopIteration:
                break
            except (EndOfFile, struct.error, RecordLengthLimitExceeded):
                # an incomplete last record (one longer than the file: it was cut off), what a kill or a writer
                # still at work leaves
                break
            except Exception as exc:  # noqa: BLE001 - a corrupt record (bad CRC, undecompressable chunk) ends the scan
                report.error = f"unreadable after byte {stream.tell()}: {type(exc).__name__}: {exc}"[:500]
                break
            if isinstance(record, Message):
                report.messages += 1
            elif isinstance(record, Header):
                report.library = record.library
            elif isinstance(record, Footer):
                report.complete = True
            on_record(record)
    return report


def parts_of(path: str | Path) -> list[Path]:
    """The files of a recording: the path and its rotated parts (<stem>_001.mcap, ...)."""
    path = Path(path)
    _check_file(path)  # the first part must exist; its error names the path given
    return recording_files(path) or [path]


class _Describe:
    """Collects one file's records into the report (ids are per file: a rotated part registers its own)."""

    def __init__(self, report: Report, part: Path) -> None:
        self.report = report
        self.part = part
        self.schemas: dict[int, str] = {}
        self.channels: dict[int, ChannelStats] = {}

    def __call__(self, record: McapRecord) -> None:
        report = self.report
        if isinstance(record, Schema):
            self.schemas[record.id] = record.name
        elif isinstance(record, Channel):
            key = (record.topic, self.schemas.get(record.schema_id, ""), record.message_encoding)
            self.channels[record.id] = report.channels.setdefault(key, ChannelStats(*key))
        elif isinstance(record, Message):
            stats = self.channels.get(record.channel_id)
            if stats is None:  # a message before (or without) its channel: counted under a placeholder
                key = (f"<unknown channel {record.channel_id}>", "", "")
                stats = self.channels[record.channel_id] = report.channels.setdefault(key, ChannelStats(*key))
            stats.times.append(record.log_time)
        elif isinstance(record, Metadata):
            report.metadata.setdefault(record.name, dict(record.metadata))
        elif isinstance(record, Attachment):
            size = len(record.data)
            report.attachments.append(
                {"name": record.name, "media_type": record.media_type, "bytes": size, "file": self.part.name}
            )


def inspect_recording(path: str | Path) -> Report:
    """Describe a recording (and its rotated parts). Raises InspectError when its first file is unreadable; a
    later part that is unreadable is reported in its FileReport.error (partial results)."""
    report = Report(path=Path(path))
    for part in parts_of(path):
        try:
            report.files.append(scan_file(part, _Describe(report, part)))
        except InspectError as exc:
            if not report.files:
                raise
            report.files.append(FileReport(path=part, error=str(exc)))
    return report


class _Copy:
    """Copies records into one writer, mapping each part's schema and channel ids to the output's."""

    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self.schema_ids: dict[tuple[str, str, bytes], int] = {}
        self.channel_ids: dict[tuple[str, str, int], int] = {}
        self.seen_meta: set[tuple[str, tuple[tuple[str, str], ...]]] = set()
        self.seen_attachments: set[tuple[str, int, int]] = set()
        self.written = 0
        self.new_part()

    def new_part(self) -> None:
        self.local_schema: dict[int, int] = {}
        self.local_channel: dict[int, int] = {}

    def __call__(self, record: McapRecord) -> None:
        writer = self.writer
        if isinstance(record, Schema):
            key = (record.name, record.encoding, bytes(record.data))
            if key not in self.schema_ids:
                self.schema_ids[key] = writer.register_schema(record.name, record.encoding, record.data)
            self.local_schema[record.id] = self.schema_ids[key]
        elif isinstance(record, Channel):
            schema_id = self.local_schema.get(record.schema_id, 0)
            ckey = (record.topic, record.message_encoding, schema_id)
            if ckey not in self.channel_ids:
                self.channel_ids[ckey] = writer.register_channel(
                    record.topic, record.message_encoding, schema_id, dict(record.metadata)
                )
            self.local_channel[record.id] = self.channel_ids[ckey]
        elif isinstance(record, Message) and record.channel_id in self.local_channel:
            channel = self.local_channel[record.channel_id]
            writer.add_message(channel, record.log_time, record.data, record.publish_time, record.sequence)
            self.written += 1
        elif isinstance(record, Metadata):
            mkey = (record.name, tuple(sorted(record.metadata.items())))
            if mkey not in self.seen_meta:
                self.seen_meta.add(mkey)
                writer.add_metadata(record.name, dict(record.metadata))
        elif isinstance(record, Attachment):
            akey = (record.name, len(record.data), hash(record.data))
            if akey not in self.seen_attachments:
                self.seen_attachments.add(akey)
                writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)


def recover(path: str | Path, out: str | Path) -> tuple[int, Report]:
    """Write every readable message, schema, channel, metadata record and attachment of a recording (all its
    parts) to one complete MCAP file with a summary at `out`. Atomic: `out` appears only when complete.
    Returns (messages written, report of the input)."""
    out = Path(out)
    inputs = parts_of(path)
    if any(out.resolve() == p.resolve() for p in inputs):
        raise InspectError(f"{out}: the output would overwrite the recording it recovers; choose another path")
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    try:
        with os.fdopen(fd, "wb") as stream:
            writer = Writer(stream, compression=CompressionType.ZSTD)
            writer.start(profile="", library="gpmppi recover")
            copy = _Copy(writer)
            report = Report(path=Path(path))
            for part in inputs:
                copy.new_part()
                describe = _Describe(report, part)
                try:
                    report.files.append(scan_file(part, lambda r, d=describe: (d(r), copy(r))))
                except InspectError as exc:
                    report.files.append(FileReport(path=part, error=str(exc)))
            writer.finish()
        os.chmod(tmp, 0o644)
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return copy.written, report


# ---- text ---------------------------------------------------------------------------------------
def _size(n: int) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024  # type: ignore[assignment]
    return f"{n} B"


def _when(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, tz=timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _short(value: str, width: int = 60) -> str:
    return value if len(value) <= width else f"<{len(value)} chars: {value[: width - 20]}...>"


def report_lines(report: Report) -> list[str]:
    """The report as text, in the manner of `mcap info`."""
    data = report.to_json()
    lines = [f"path:        {report.path}" + (f" ({len(report.files)} rotated parts)" if len(report.files) > 1 else "")]
    for f in report.files:
        if f.error and not f.messages:
            state = f"UNREADABLE: {f.error}"
        elif f.truncated:
            state = (
                f"TRUNCATED: no summary (the recorder was killed, or is still writing); "
                f"{f.messages} messages recovered from complete chunks"
            )
            state += f"; {f.error}" if f.error else ""
        else:
            state = f"complete, {f.messages} messages"
        lines.append(f"  {f.path.name:<28} {_size(f.bytes):>9}  {state}")
    library = sorted({f.library for f in report.files if f.library})
    lines.append(f"library:     {', '.join(library) or '?'}")
    lines.append(f"messages:    {data['messages']}" + (" (truncated)" if report.truncated else ""))
    lines.append(f"duration:    {data['duration_s']:.3f} s")
    if data["messages"]:
        lines.append(f"start:       {_when(data['start_ns'])}  ({data['start_ns']} ns)")
        lines.append(f"end:         {_when(data['end_ns'])}  ({data['end_ns']} ns)")
    channels = data["channels"]
    lines.append(f"channels:    {len(channels)}")
    if channels:
        width = max(len(c["topic"]) for c in channels)
        sw = max(12, *(len(c["schema"] or c["encoding"]) + 2 for c in channels))
        lines.append(
            f"  {'topic':<{width}}  {'schema':<{sw}} {'count':>8} {'rate_hz':>9} {'first_s':>9} {'last_s':>9} "
            f"{'max_gap_s':>9}  gap_at_s"
        )
        for c in channels:
            schema = c["schema"] or f"({c['encoding'] or 'none'})"
            lines.append(
                f"  {c['topic']:<{width}}  {schema:<{sw}} {c['count']:>8} {c['rate_hz']:>9.2f} {c['first_s']:>9.3f} "
                f"{c['last_s']:>9.3f} {c['max_gap_s']:>9.3f}  {c['max_gap_at_s']:.3f}"
            )
    lines.append(f"metadata:    {len(report.metadata)}")
    for name, values in report.metadata.items():
        lines.append(f"  {name}: " + " ".join(f"{k}={_short(v)}" for k, v in values.items()))
    lines.append(f"attachments: {len(report.attachments)}")
    for a in report.attachments:
        lines.append(f"  {a['name']:<36} {a['media_type']:<26} {_size(a['bytes']):>9}  ({a['file']})")
    for error in data["errors"]:
        lines.append(f"error:       {error}")
    return lines
