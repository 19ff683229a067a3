"""Reading a recording for replay: checked opening, raw records in log-time order, run metadata and attachments.

Built on `services.recording.mcap_io` (its rotated-part listing and its reader, which recovers the complete chunks of an
unfinished file). What is added here is what a player needs and the recorder's reader does not give: the raw
payload with its log time (republished as recorded, not re-encoded), a clear error for a file that is not a
recording at all, and the metadata / attachments the recorder stores (`gpmppi.run`, `gpmppi.settings.<name>`,
`launch.yaml`, `model/<basename>`), read with the summary's index or, for an unfinished file, by a linear scan.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.reader import make_reader
from mcap.records import Attachment, Metadata
from mcap.stream_reader import StreamReader

from services.recording.mcap_io import _iter_raw, recording_files

log = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
RUN_METADATA = "gpmppi.run"
SETTINGS_PREFIX = "gpmppi.settings."
QUARANTINE_SUFFIX = "/_rejected"


class LogError(ValueError):
    """A file that cannot be replayed (missing, empty, not MCAP, no messages); the message says which and why."""


@dataclass(frozen=True)
class Record:
    """One recorded message as stored: its key (topic), receive time, header stamp and raw JSON payload."""

    key: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes
    schema: str | None


@dataclass
class RunInfo:
    """What the recorder stored about the run (empty dicts for a log without metadata)."""

    run: dict[str, str] = field(default_factory=dict)
    # service name -> (kind, resolved settings)
    settings: dict[str, tuple[str, dict]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)


def check_log(path: str | Path) -> list[Path]:
    """The parts of the recording at `path`, each checked to be an MCAP file; LogError naming the problem."""
    path = Path(path)
    if not path.exists():
        raise LogError(f"{path}: no such file; give the .mcap file the recorder wrote")
    if not path.is_file():
        raise LogError(f"{path} is not a file; give the .mcap file the recorder wrote")
    parts = recording_files(path) or [path]
    for part in parts:
        with open(part, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
        if not head:
            raise LogError(f"{part} is empty (0 bytes): nothing was recorded into it")
        if head != MCAP_MAGIC:
            raise LogError(f"{part} is not an MCAP file (it does not start with the MCAP magic bytes)")
    return parts


def iter_records(parts: list[Path]) -> Iterator[Record]:
    """Every message of the recording in log-time order (parts one after the other), as raw records."""
    for part in parts:
        for topic, schema, msg in _iter_raw(part, None):
            yield Record(topic, int(msg.log_time), int(msg.publish_time), bytes(msg.data), schema)


def log_span_ns(parts: list[Path]) -> tuple[int, int] | None:
    """(first, last) log time of the recording from the summaries' statistics, or None when a part has none
    (an unfinished file): then the span is only known once it has been read."""
    first, last = None, None
    for part in parts:
        with open(part, "rb") as f:
            try:
                summary = make_reader(f).get_summary()
            except Exception:  # noqa: BLE001 - an unfinished file has no usable summary
                return None
            if summary is None or summary.statistics is None or summary.statistics.message_count == 0:
                if summary is None or summary.statistics is None:
                    return None
                continue
            s = summary.statistics
            first = s.message_start_time if first is None else min(first, s.message_start_time)
            last = s.message_end_time if last is None else max(last, s.message_end_time)
    return None if first is None or last is None else (int(first), int(last))


def _scan_extras(part: Path) -> tuple[list[Metadata], list[Attachment]]:
    """Metadata and attachments of a file without a readable summary, by a linear scan (stops at a torn end)."""
    metadata: list[Metadata] = []
    attachments: list[Attachment] = []
    with open(part, "rb") as f:
        records = StreamReader(f, skip_magic=False).records
        while True:
            try:
                record = next(records)
            except StopIteration:
                break
            except Exception:  # noqa: BLE001 - a truncated tail ends the scan
                break
            if isinstance(record, Metadata):
                metadata.append(record)
            elif isinstance(record, Attachment):
                attachments.append(record)
    return metadata, attachments


def read_run_info(parts: list[Path]) -> RunInfo:
    """The run metadata, per-service settings and attachments of a recording (the first part that has them)."""
    info = RunInfo()
    for part in parts:
        with open(part, "rb") as f:
            try:
                reader = make_reader(f)
                reader.get_summary()
                metadata = list(reader.iter_metadata())
                attachments = list(reader.iter_attachments())
            except Exception:  # noqa: BLE001 - no summary: scan the file
                metadata, attachments = _scan_extras(part)
        for m in metadata:
            if m.name == RUN_METADATA and not info.run:
                info.run = dict(m.metadata)
            elif m.name.startswith(SETTINGS_PREFIX):
                name = m.name[len(SETTINGS_PREFIX):]
                if name in info.settings:
                    continue
                kind = m.metadata.get("kind", name)
                try:
                    settings = json.loads(m.metadata.get("settings", "{}"))
                except ValueError as exc:
                    raise LogError(f"{part}: metadata {m.name!r} holds settings that are not JSON ({exc})") from exc
                if not isinstance(settings, dict):
                    raise LogError(f"{part}: metadata {m.name!r} holds settings that are not a JSON object")
                info.settings[name] = (kind, settings)
        for a in attachments:
            info.attachments.setdefault(a.name, bytes(a.data))
    return info


def robots_in(keys: set[str]) -> list[str]:
    """The robot names of `gpmppi/{robot}/...` keys, most frequent first."""
    counts: dict[str, int] = {}
    for key in keys:
        parts = key.split("/")
        if len(parts) >= 3 and parts[0] == "gpmppi":
            counts[parts[1]] = counts.get(parts[1], 0) + 1
    return sorted(counts, key=lambda r: -counts[r])


def keys_and_services(parts: list[Path]) -> tuple[set[str], set[str]]:
    """(every key in the recording, the service names that sent heartbeats), from the channel list."""
    keys: set[str] = set()
    for part in parts:
        with open(part, "rb") as f:
            try:
                summary = make_reader(f).get_summary()
            except Exception:  # noqa: BLE001
                summary = None
        if summary is not None:
            keys |= {c.topic for c in summary.channels.values()}
        else:
            keys |= {r.key for r in iter_records([part])}
    services = {k.split("/")[3] for k in keys if len(k.split("/")) == 4 and k.split("/")[2] == "health"}
    return keys, services
