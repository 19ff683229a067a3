"""recorder: everything under `gpmppi/**` to MCAP, as received (JSON + JSON Schema; Foxglove opens it).

The subscription uses a FIFO channel, which never drops: when it is full Zenoh waits for us instead.
Chunks are flushed as they fill (and at least every `flush_interval_s`), so a crash loses at most the last
chunk; files rotate by size or duration.
"""

from __future__ import annotations

import time

import zenoh
from pydantic import Field

from services.mcap_io import McapWriter
from services.node import Node, NodeSettings


class Settings(NodeSettings):
    service: str = Field("recorder", description="service name")
    path: str = Field("runs/recording.mcap", description="output MCAP file (rotated parts get _001, _002, ...)")
    key_expr: str = Field("gpmppi/**", description="what to record")
    queue_capacity: int = Field(100_000, gt=0, description="FIFO capacity (full: the sender waits, nothing drops)")
    chunk_size: int = Field(256 * 1024, gt=0, description="MCAP chunk size [bytes]")
    flush_interval_s: float = Field(1.0, gt=0, description="flush a partial chunk after this long [s]")
    max_bytes: int | None = Field(None, description="rotate past this file size [bytes] (None: never)")
    max_duration_s: float | None = Field(None, description="rotate past this file age [s] (None: never)")
    compression: str = Field("zstd", description="chunk compression: zstd, lz4 or none")


def run(settings: Settings) -> int:
    writer = McapWriter(
        settings.path,
        chunk_size=settings.chunk_size,
        flush_interval_s=settings.flush_interval_s,
        max_bytes=settings.max_bytes,
        max_duration_s=settings.max_duration_s,
        compression=settings.compression,
    )
    try:
        with Node(settings) as node:
            assert node.session is not None
            sub = node.session.declare_subscriber(
                settings.key_expr, zenoh.handlers.FifoChannel(settings.queue_capacity)
            )
            node.log.info("recording %s to %s", settings.key_expr, settings.path)

            def drain() -> int:
                n = 0
                while (sample := sub.try_recv()) is not None:
                    if sample.kind != zenoh.SampleKind.PUT:
                        continue
                    writer.write_bytes(str(sample.key_expr), sample.payload.to_bytes(), log_time_ns=time.time_ns())
                    n += 1
                node.counters.received += n
                return n

            while node.ok():
                if drain():
                    node.cycle()
                writer.flush_if_due()  # a quiet stream still reaches the disk within flush_interval_s
                node.spin_once()
            drain()  # what arrived before the stop
    finally:
        writer.close()
    return 0
