"""Writing gpmppi messages to MCAP (`McapWriter`; the layout it writes is `services.recording.mcap_io`'s).

Data is chunked, and each finished chunk is flushed to the operating system, so a crash
loses at most the chunk in progress (bounded by `chunk_size` bytes and `flush_interval_s`).

Rotation (for the recorder): with `max_bytes` or `max_duration_s`, the writer closes the current
file and continues in `<stem>_001.mcap`, `<stem>_002.mcap`, ... . Metadata records are repeated at the start of
every part.

`McapWriter.record` is the recorder's entry: what fails its key's model goes raw to the schema-less
quarantine channel `<key>/_rejected`, so every message on a schema'd channel meets its JSON Schema.
"""

from __future__ import annotations

import errno
import json
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from types import TracebackType
from typing import IO, TypeVar

from mcap.writer import CompressionType, Writer
from pydantic import ValidationError

from schemas import Message, encode, model_for_key
from schemas.codec import MAX_PAYLOAD_BYTES
from services.recording.mcap_io import (
    LIBRARY,
    PROFILE,
    RAW_ENCODING,
    REJECTED_SUFFIX,
    rejected_topic,
    rotated_path,
    schema_name,
)

M = TypeVar("M", bound=Message)


class McapWriter:
    """Writes gpmppi messages to MCAP; a context manager. Not thread-safe: use it from one thread.

    path: output file (its folder is created); it must not exist: the writer never overwrites (FileExistsError),
    and a rotated part that exists already stops the writer like a write error (`failed` names it).
    chunk_size: bytes per chunk before it is written out.
    flush_interval_s: a chunk older than this is written out at the next write, so a slow stream also
    reaches the disk. max_bytes / max_duration_s: rotate to a new file past this size / age (None: never).
    compression: "zstd", "lz4" or "none".

    A write that fails in the operating system (disk full, file-size limit) raises `OSError` once; the
    writer is then `failed` (its message says why), what reached the file reads back (linear recovery),
    and later writes raise `RuntimeError`.
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
        self._models: dict[str, type[Message] | None] = {}
        self._foreign: dict[str, tuple[str, str, bytes, str]] = {}  # topic -> its schema and message encoding
        self._metadata: list[tuple[str, dict[str, str]]] = []  # repeated at the start of every rotated part
        self._pending_bytes = 0
        self._data_start = 0
        self._last_flush = 0.0
        self._opened_at = 0.0
        self.files: list[Path] = []
        self.messages_written = 0
        self.quarantined = 0
        self.failed: str | None = None  # why writing stopped (disk full, file-size limit), or None
        self.failed_errno: int | None = None  # its errno (EEXIST: a rotated part's name was taken)
        self._open()

    # ---- file lifecycle -------------------------------------------------------------------
    def _open(self) -> None:
        target = rotated_path(self.path, self._index)
        target.parent.mkdir(parents=True, exist_ok=True)
        # exclusive create: a recording never overwrites a file (an earlier run's, or a part of one), on rotation
        # too; FileExistsError names the file
        self._stream = open(target, "xb")  # noqa: SIM115 - closed in _close_file
        self._writer = Writer(self._stream, chunk_size=self._chunk_size, compression=self._compression)
        self.files.append(target)
        self._guarded(lambda: self._start_part())

    def _start_part(self) -> None:
        assert self._writer is not None and self._stream is not None
        self._writer.start(profile=PROFILE, library=LIBRARY)
        for name, data in self._metadata:
            self._writer.add_metadata(name, data)
        self._stream.flush()
        self._schemas.clear()
        self._channels.clear()
        self._pending_bytes = 0
        self._data_start = self._stream.tell()  # rotation by size counts the data, not the preamble
        self._last_flush = self._opened_at = time.monotonic()

    def _close_file(self) -> None:
        writer, stream = self._writer, self._stream
        self._writer = None
        self._stream = None
        if writer is not None and stream is not None:
            try:
                writer.finish()
                stream.close()
            except OSError as exc:
                self._fail(exc, stream)
                raise

    def _fail(self, exc: OSError, stream: IO[bytes] | None) -> None:
        """Stop writing after an operating-system error; what reached the file stays readable."""
        where = f" {exc.filename}" if exc.filename else ""
        self.failed = f"{exc.strerror or exc}{where} (errno {errno.errorcode.get(exc.errno or 0, exc.errno)})"
        self.failed_errno = exc.errno
        self._writer = None
        self._stream = None
        if stream is not None:
            try:
                stream.close()  # flushing the buffer fails again; the descriptor is closed regardless
            except OSError:
                pass

    def _guarded(self, action: Callable[[], None]) -> None:
        try:
            action()
        except OSError as exc:
            self._fail(exc, self._stream)
            raise

    def _maybe_rotate(self) -> None:
        assert self._stream is not None
        size = self._stream.tell() - self._data_start + self._pending_bytes
        too_big = self._max_bytes is not None and size >= self._max_bytes
        too_old = self._max_duration_s is not None and time.monotonic() - self._opened_at >= self._max_duration_s
        if (too_big or too_old) and self.messages_written > 0:
            self._close_file()
            self._index += 1
            self._open()

    def _check_open(self) -> None:
        if self.failed is not None:
            raise RuntimeError(f"McapWriter for {self.path} stopped after a write error: {self.failed}")
        if self._writer is None:
            raise RuntimeError(f"McapWriter for {self.path} is closed; open a new one to write more")

    # ---- metadata and attachments -----------------------------------------------------------
    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """A metadata record (string -> string), written now and again at the start of every rotated part."""
        self._check_open()
        record = {str(k): str(v) for k, v in data.items()}
        self._metadata.append((name, record))
        assert self._writer is not None and self._stream is not None
        writer, stream = self._writer, self._stream
        self._guarded(lambda: (writer.add_metadata(name, record), stream.flush()))

    def add_attachment(self, name: str, data: bytes, media_type: str, create_time_ns: int = 0) -> None:
        """A file attached to the part now open (attachments are not repeated in later parts: they may be big)."""
        self._check_open()
        assert self._writer is not None and self._stream is not None
        writer, stream = self._writer, self._stream
        now = time.time_ns()
        self._guarded(
            lambda: (writer.add_attachment(create_time_ns, now, name, media_type, bytes(data)), stream.flush())
        )

    # ---- writing --------------------------------------------------------------------------
    def _channel(self, topic: str, model: type[Message] | None, encoding: str) -> int:
        assert self._writer is not None
        if topic in self._channels:
            return self._channels[topic]
        schema_id = 0
        if model is not None:
            name = schema_name(model)
            if name not in self._schemas:
                schema = json.dumps(model.model_json_schema()).encode()
                self._schemas[name] = self._writer.register_schema(name=name, encoding="jsonschema", data=schema)
            schema_id = self._schemas[name]
        self._channels[topic] = self._writer.register_channel(
            topic=topic, message_encoding=encoding, schema_id=schema_id
        )
        return self._channels[topic]

    def _foreign_channel(self, topic: str) -> int:
        assert self._writer is not None
        if topic not in self._channels:
            name, schema_encoding, data, encoding = self._foreign[topic]
            if name not in self._schemas:
                self._schemas[name] = self._writer.register_schema(name=name, encoding=schema_encoding, data=data)
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=encoding, schema_id=self._schemas[name]
            )
        return self._channels[topic]

    def write_encoded(
        self,
        topic: str,
        schema: tuple[str, str, bytes],
        message_encoding: str,
        payload: bytes,
        log_time_ns: int,
        publish_time_ns: int | None = None,
    ) -> None:
        """Record a message of another schema family on its own channel: `schema` is (name, encoding, data), e.g.
        Foxglove's scene (`foxglove.SceneUpdate`, protobuf). The topic keeps the schema it was first written with."""
        self._check_open()
        self._guarded(self._maybe_rotate)
        self._foreign.setdefault(topic, (*schema, message_encoding))
        assert self._writer is not None
        writer = self._writer
        channel_id = self._foreign_channel(topic)
        sequence = self._sequences.get(topic, 0)
        self._sequences[topic] = sequence + 1
        log_time = int(log_time_ns)
        publish_time = log_time if publish_time_ns is None else int(publish_time_ns)
        self._guarded(
            lambda: writer.add_message(
                channel_id=channel_id, log_time=log_time, data=payload, publish_time=publish_time,
                sequence=sequence & 0xFFFFFFFF,
            )
        )  # fmt: skip
        self.messages_written += 1
        self._pending_bytes += len(payload)
        if self._pending_bytes >= self._chunk_size or time.monotonic() - self._last_flush >= self._flush_interval_s:
            self.flush()

    def _model(self, key: str) -> type[Message] | None:
        if key not in self._models:
            try:
                self._models[key] = None if key.endswith(REJECTED_SUFFIX) else model_for_key(key)
            except KeyError:
                self._models[key] = None
        return self._models[key]

    def write(self, key: str, msg: Message, log_time_ns: int | None = None) -> None:
        """Record `msg` on topic `key`; log time defaults to now (publish time is the header stamp)."""
        self.write_bytes(
            key, encode(msg), type(msg), log_time_ns, publish_time_ns=msg.header.stamp_ns, sequence=msg.header.seq
        )

    def write_bytes(
        self,
        key: str,
        payload: bytes,
        model: type[Message] | None = None,
        log_time_ns: int | None = None,
        publish_time_ns: int | None = None,
        sequence: int | None = None,
    ) -> None:
        """Record an already-encoded, already-valid JSON payload on its key's channel (not re-encoded, not
        checked: use `record` for input from the network)."""
        self._write(key, model or self._model(key), "json", payload, log_time_ns, publish_time_ns, sequence)

    def record(self, key: str, payload: bytes, log_time_ns: int, max_payload_bytes: int = MAX_PAYLOAD_BYTES) -> bool:
        """Record a payload as received on `key`, keeping every channel true to what it declares.

        A key with a registered model: a payload that validates (strictly, so it also meets the channel's
        JSON Schema) goes on `key` with publish time = header stamp and sequence = header seq; anything else
        goes, raw, to the schema-less `<key>/_rejected` channel. A key with no model: JSON goes on `key`
        (schema-less JSON); anything else to `<key>/_rejected`. Returns False when it was quarantined."""
        model = self._model(key)
        if key.endswith(REJECTED_SUFFIX):
            self._write(key, None, RAW_ENCODING, payload, log_time_ns, None, None)
            return False
        if model is not None:
            msg = _strict_decode(model, payload, max_payload_bytes)
            if msg is not None:
                self._write(key, model, "json", payload, log_time_ns, msg.header.stamp_ns, msg.header.seq)
                return True
        elif len(payload) <= max_payload_bytes and _is_json(payload):
            self._write(key, None, "json", payload, log_time_ns, None, None)
            return True
        self._write(rejected_topic(key), None, RAW_ENCODING, payload, log_time_ns, None, None)
        self.quarantined += 1
        return False

    def _write(
        self,
        topic: str,
        model: type[Message] | None,
        encoding: str,
        payload: bytes,
        log_time_ns: int | None,
        publish_time_ns: int | None,
        sequence: int | None,
    ) -> None:
        self._check_open()
        self._guarded(self._maybe_rotate)
        assert self._writer is not None
        writer = self._writer
        channel_id = self._channel(topic, model, encoding)
        log_time = time.time_ns() if log_time_ns is None else int(log_time_ns)
        if sequence is None:  # no header: a count of this channel's messages
            sequence = self._sequences.get(topic, 0)
            self._sequences[topic] = sequence + 1
        publish_time = log_time if publish_time_ns is None else int(publish_time_ns)
        self._guarded(
            lambda: writer.add_message(
                channel_id=channel_id, log_time=log_time, data=payload, publish_time=publish_time,
                sequence=int(sequence) & 0xFFFFFFFF,  # MCAP sequence is uint32
            )
        )
        self.messages_written += 1
        self._pending_bytes += len(payload)
        if self._pending_bytes >= self._chunk_size or time.monotonic() - self._last_flush >= self._flush_interval_s:
            self.flush()

    def flush(self) -> None:
        """Write out the chunk in progress and hand it to the operating system."""
        if self._writer is None:
            return
        self._guarded(self._writer.flush)
        self._pending_bytes = 0
        self._last_flush = time.monotonic()

    def flush_if_due(self) -> None:
        """Flush when data has waited longer than `flush_interval_s` (call it when the input is quiet)."""
        if self._pending_bytes and time.monotonic() - self._last_flush >= self._flush_interval_s:
            self.flush()

    def close(self) -> None:
        """Finish the file (summary + index) and close it; safe to call twice (and after a failure)."""
        self._close_file()

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def _strict_decode(model: type[M], payload: bytes, max_bytes: int) -> M | None:
    """The message, or None when the payload is not a valid `model`. Strict: a number sent as a string, which
    lenient parsing would coerce, is invalid too, since the stored bytes must meet the JSON Schema."""
    if len(payload) > max_bytes:
        return None
    try:
        return model.model_validate_json(payload, strict=True)
    except (ValidationError, RecursionError, ValueError):
        return None


def _no_constant(name: str) -> object:
    raise ValueError(f"{name} is not JSON")


def _is_json(payload: bytes) -> bool:
    """Standard JSON (NaN / Infinity, which Python's parser accepts, are not)."""
    try:
        json.loads(payload, parse_constant=_no_constant)
    except (ValueError, RecursionError, UnicodeDecodeError):
        return False
    return True

