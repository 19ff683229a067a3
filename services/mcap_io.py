"""MCAP recording and reading of gpmppi messages.

Messages are stored as JSON (`message_encoding="json"`) with the pydantic model's JSON Schema
(`schema encoding="jsonschema"`), so Foxglove and the `mcap` CLI open the files without any
plugin. Data is chunked, and each finished chunk is flushed to the operating system, so a crash
loses at most the chunk in progress (bounded by `chunk_size` bytes and `flush_interval_s`).
A file that was never closed (a crash) is still read back by `read_messages`: every complete
chunk is recovered by a linear scan.

Rotation (for the recorder): with `max_bytes` or `max_duration_s`, the writer closes the current
file and continues in `<stem>_001.mcap`, `<stem>_002.mcap`, ... ; `recording_files(path)` lists
the parts of a recording in order.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import TracebackType
from typing import IO

from mcap.reader import make_reader
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from schemas import DecodeError, Message, decode, encode, model_for_key
from schemas.messages import MODELS

log = logging.getLogger(__name__)

PROFILE = ""  # no ROS profile: plain JSON messages
LIBRARY = "gpmppi"
SCHEMA_PREFIX = "gpmppi."


def schema_name(model: type[Message]) -> str:
    return SCHEMA_PREFIX + model.__name__


def _rotated_path(path: Path, index: int) -> Path:
    return path if index == 0 else path.with_name(f"{path.stem}_{index:03d}{path.suffix}")


def recording_files(path: str | Path) -> list[Path]:
    """The existing parts of a (possibly rotated) recording, in order: path, <stem>_001, ..."""
    path = Path(path)
    parts: list[Path] = []
    index = 0
    while _rotated_path(path, index).is_file():
        parts.append(_rotated_path(path, index))
        index += 1
    return parts


class McapWriter:
    """Writes gpmppi messages to MCAP; a context manager. Not thread-safe: use it from one thread.

    path: output file (its folder is created). chunk_size: bytes per chunk before it is written out.
    flush_interval_s: a chunk older than this is written out at the next write, so a slow stream also
    reaches the disk. max_bytes / max_duration_s: rotate to a new file past this size / age (None: never).
    compression: "zstd", "lz4" or "none".
    """

    def __init__(
        self,
        path: str | Path,
        *,
        chunk_size: int = 256 * 1024,
        flush_interval_s: float = 1.0,
        max_bytes: int | None = None,
        max_duration_s: float | None = None,
        compression: str = "zstd",
    ) -> None:
        if chunk_size <= 0 or flush_interval_s <= 0:
            raise ValueError(f"chunk_size ({chunk_size}) and flush_interval_s ({flush_interval_s}) must be positive")
        if max_bytes is not None and max_bytes <= 0:
            raise ValueError(f"max_bytes must be positive or None, got {max_bytes}")
        if max_duration_s is not None and max_duration_s <= 0:
            raise ValueError(f"max_duration_s must be positive or None, got {max_duration_s}")
        compressions = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        if compression not in compressions:
            raise ValueError(f"compression {compression!r} is not one of {sorted(compressions)}")
        self.path = Path(path)
        self._compression = compressions[compression]
        self._chunk_size = chunk_size
        self._flush_interval_s = flush_interval_s
        self._max_bytes = max_bytes
        self._max_duration_s = max_duration_s
        self._index = 0
        self._stream: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequences: dict[str, int] = {}
        self._pending_bytes = 0
        self._last_flush = 0.0
        self._opened_at = 0.0
        self.files: list[Path] = []
        self.messages_written = 0
        self._open()

    # ---- file lifecycle -------------------------------------------------------------------
    def _open(self) -> None:
        target = _rotated_path(self.path, self._index)
        target.parent.mkdir(parents=True, exist_ok=True)
        self._stream = open(target, "wb")  # noqa: SIM115 - closed in _close_file
        self._writer = Writer(self._stream, chunk_size=self._chunk_size, compression=self._compression)
        self._writer.start(profile=PROFILE, library=LIBRARY)
        self._stream.flush()
        self._schemas.clear()
        self._channels.clear()
        self._pending_bytes = 0
        self._last_flush = self._opened_at = time.monotonic()
        self.files.append(target)

    def _close_file(self) -> None:
        if self._writer is not None and self._stream is not None:
            self._writer.finish()
            self._stream.close()
        self._writer = None
        self._stream = None

    def _maybe_rotate(self) -> None:
        assert self._stream is not None
        too_big = self._max_bytes is not None and self._stream.tell() + self._pending_bytes >= self._max_bytes
        too_old = self._max_duration_s is not None and time.monotonic() - self._opened_at >= self._max_duration_s
        if (too_big or too_old) and self.messages_written > 0:
            self._close_file()
            self._index += 1
            self._open()

    # ---- writing --------------------------------------------------------------------------
    def _channel(self, key: str, model: type[Message] | None) -> int:
        assert self._writer is not None
        if key in self._channels:
            return self._channels[key]
        schema_id = 0
        if model is not None:
            name = schema_name(model)
            if name not in self._schemas:
                schema = json.dumps(model.model_json_schema()).encode()
                self._schemas[name] = self._writer.register_schema(name=name, encoding="jsonschema", data=schema)
            schema_id = self._schemas[name]
        self._channels[key] = self._writer.register_channel(topic=key, message_encoding="json", schema_id=schema_id)
        return self._channels[key]

    def write(self, key: str, msg: Message, log_time_ns: int | None = None) -> None:
        """Record `msg` on topic `key`; log time defaults to now (publish time is the header stamp)."""
        self.write_bytes(key, encode(msg), type(msg), log_time_ns, publish_time_ns=msg.header.stamp_ns)

    def write_bytes(
        self,
        key: str,
        payload: bytes,
        model: type[Message] | None = None,
        log_time_ns: int | None = None,
        publish_time_ns: int | None = None,
    ) -> None:
        """Record an already-encoded JSON payload as received (the recorder does not re-encode)."""
        if self._writer is None:
            raise RuntimeError(f"McapWriter for {self.path} is closed; open a new one to write more")
        self._maybe_rotate()
        if model is None:
            try:
                model = model_for_key(key)
            except KeyError:
                model = None
        channel_id = self._channel(key, model)
        now_ns = time.time_ns()
        log_time = now_ns if log_time_ns is None else int(log_time_ns)
        sequence = self._sequences.get(key, 0)
        self._sequences[key] = sequence + 1
        self._writer.add_message(
            channel_id=channel_id,
            log_time=log_time,
            data=payload,
            publish_time=log_time if publish_time_ns is None else int(publish_time_ns),
            sequence=sequence,
        )
        self.messages_written += 1
        self._pending_bytes += len(payload)
        if self._pending_bytes >= self._chunk_size or time.monotonic() - self._last_flush >= self._flush_interval_s:
            self.flush()

    def flush(self) -> None:
        """Write out the chunk in progress and hand it to the operating system."""
        if self._writer is None:
            return
        self._writer.flush()
        self._pending_bytes = 0
        self._last_flush = time.monotonic()

    def flush_if_due(self) -> None:
        """Flush when data has waited longer than `flush_interval_s` (call it when the input is quiet)."""
        if self._pending_bytes and time.monotonic() - self._last_flush >= self._flush_interval_s:
            self.flush()

    def close(self) -> None:
        """Finish the file (summary + index) and close it; safe to call twice."""
        self._close_file()

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


# ---- reading ----------------------------------------------------------------------------------
def _iter_raw(path: Path, keys: set[str] | None) -> Iterator[tuple[str, str | None, McapMessage]]:
    """(topic, schema name, record) in log-time order; falls back to a linear scan for unfinished files."""
    with open(path, "rb") as stream:
        try:
            reader = make_reader(stream)
            summary = reader.get_summary()
        except Exception as exc:  # noqa: BLE001 - any failure here means no usable footer/summary
            log.warning("%s has no readable summary (%s); recovering complete chunks by a linear scan", path, exc)
            summary = None
        if summary is not None:
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


def read_messages(path: str | Path, keys: Iterable[str] | None = None) -> Iterator[tuple[str, int, Message]]:
    """(key, log_time_ns, decoded message) for every message in the recording at `path`.

    `keys` limits the topics (exact keys). Messages on keys with no registered model, or that do not
    decode, are skipped with a warning (a recording keeps what was on the wire, valid or not).
    Rotated parts (`<stem>_001.mcap`, ...) are read after `path`.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no MCAP recording at {path}")
    wanted = set(keys) if keys is not None else None
    by_name = {schema_name(m): m for m in MODELS.values()}
    for part in recording_files(path) or [path]:
        for topic, name, record in _iter_raw(part, wanted):
            model = by_name.get(name) if name else None
            try:
                model = model or model_for_key(topic)
                yield topic, record.log_time, decode(model, record.data)
            except (KeyError, DecodeError) as exc:
                log.warning("%s: skipped a message on %s: %s", part, topic, exc)
