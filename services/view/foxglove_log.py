"""A recording with its Foxglove scene added, offline (`gpmppi replay LOG --foxglove-scene OUT.mcap`): every record
of the log (all its parts: messages, quarantine, metadata, attachments) copied unchanged into one new MCAP file,
and beside them the scene channels that the recorder writes with `foxglove_scene: true`, from the same mapping
(`services.view.foxglove_scene`), at the log times of the messages they come from."""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any

from mcap.records import Channel, Message, Schema
from mcap.writer import CompressionType, Writer

from schemas import DecodeError, decode, model_for_key
from schemas.messages import MODELS
from services.recording.mcap_inspect import _Copy, parts_of, scan_file
from services.recording.mcap_io import FOXGLOVE_SCHEMA_PREFIX, REJECTED_SUFFIX, schema_name
from services.view.foxglove_scene import FoxgloveSceneMapper, schema_of
from services.view.geometry import Decimation


def add_scene(log: str | Path, out: str | Path, options: Decimation | None = None) -> dict[str, Any]:
    """Write `log` and its Foxglove scene to `out` (atomically: a temporary file renamed when complete). A scene
    already in the log is copied as it is, not drawn twice. Returns {"messages", "scene_messages", "wall_s",
    "output"}."""
    t0 = time.monotonic()
    out = Path(out)
    inputs = parts_of(log)
    if any(out.resolve() == p.resolve() for p in inputs):
        raise ValueError(f"{out}: the output would overwrite the recording it reads; choose another path")
    mapper = FoxgloveSceneMapper(options)
    by_name = {schema_name(m): m for m in MODELS.values()}
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent)
    scene_channels: dict[str, int] = {}
    scene_written = 0
    try:
        with os.fdopen(fd, "wb") as stream:
            writer = Writer(stream, compression=CompressionType.ZSTD)
            writer.start(profile="", library="gpmppi replay --foxglove-scene")
            copy = _Copy(writer)
            schemas: dict[int, str] = {}
            channels: dict[int, tuple[str, str]] = {}  # channel id -> (topic, schema name)
            had_scene = False

            def on_record(record: Any) -> None:
                nonlocal scene_written, had_scene
                copy(record)
                if isinstance(record, Schema):
                    schemas[record.id] = record.name
                elif isinstance(record, Channel):
                    name = schemas.get(record.schema_id, "")
                    had_scene |= name.startswith(FOXGLOVE_SCHEMA_PREFIX)
                    channels[record.id] = (record.topic, name)
                elif isinstance(record, Message) and record.channel_id in channels and not had_scene:
                    topic, name = channels[record.channel_id]
                    if topic.endswith(REJECTED_SUFFIX):
                        return
                    try:
                        msg = decode(by_name.get(name) or model_for_key(topic), bytes(record.data))
                    except (KeyError, DecodeError):
                        return
                    for scene in mapper.map(topic, msg, record.log_time):
                        if scene.topic not in scene_channels:
                            s = schema_of(scene.topic)
                            schema_id = writer.register_schema(s.name, s.encoding, bytes(s.data))
                            scene_channels[scene.topic] = writer.register_channel(scene.topic, "protobuf", schema_id)
                        writer.add_message(
                            scene_channels[scene.topic], record.log_time, scene.data, scene.stamp_ns, scene_written
                        )
                        scene_written += 1

            for part in inputs:
                copy.new_part()
                scan_file(part, on_record)
            writer.finish()
        os.chmod(tmp, 0o644)
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return {
        "messages": copy.written,
        "scene_messages": scene_written,
        "wall_s": round(time.monotonic() - t0, 3),
        "output": str(out),
    }
