"""recorder: everything under `gpmppi/**` to MCAP (JSON + JSON Schema; Foxglove opens it).

- Every channel holds what it declares: a payload that fails its key's model is written raw to the
  schema-less `<key>/_rejected` channel (counted as `quarantined` in the heartbeat), never onto the key's own
  schema'd channel. Keys with no registered model are recorded as schema-less JSON on their own key.
- Record fields: log time = receive time, publish time = header stamp, sequence = header seq.
- Run metadata (`gpmppi.run`), each service's resolved settings (`gpmppi.settings.<name>`) and attachments
  (`launch.yaml`, `model/<file>`, and each learned profile a `ModelUpdate` announces as `learned/<sha256>.npz`): see
  `services.recording.recorder_meta`.
- The subscription is a FIFO channel, which never drops: when it is full Zenoh waits for us instead.
  Chunks are flushed at least every `flush_interval_s`, so a SIGKILL loses at most about that long;
  SIGINT / SIGTERM finish the file (summary and index). Files rotate by size or duration.
- With `foxglove_scene`, the Foxglove scene (`services.view.foxglove_scene`: pose and transforms, lane, obstacles,
  plan, rollouts, in Foxglove's own schemas) is written beside the messages, so Foxglove's 3D panel shows the
  recording with nothing converted.
- A write error (disk full, file-size limit) is logged once; the file so far stays readable, and the
  recorder keeps running (draining its input, so no publisher ever waits on it) with status "failing".
"""

from __future__ import annotations

import errno
import signal
import time
from concurrent import futures
from concurrent.futures import Future, ThreadPoolExecutor

import zenoh
from pydantic import Field

from schemas import DecodeError, decode, model_for_key
from services.recording.mcap_io import REJECTED_SUFFIX, McapWriter
from services.recording.recorder_meta import (
    MODEL_UPDATE_SUFFIX,
    RunRecord,
    ServiceConfig,
    learned_attachment,
    resolve_run_record,
)
from services.runtime.node import Node
from services.runtime.node_settings import NodeSettings
from services.view.foxglove_scene import FoxgloveSceneMapper, scene_feeds, schema_of


class Settings(NodeSettings):
    service: str = Field("recorder", description="service name")
    path: str = Field("runs/recording.mcap", description="output MCAP file (rotated parts get _001, _002, ...)")
    key_expr: str = Field("gpmppi/**", description="what to record")
    queue_capacity: int = Field(100_000, gt=0, description="FIFO capacity (full: the sender waits, nothing drops)")
    chunk_size: int = Field(256 * 1024, gt=0, description="MCAP chunk size [bytes]")
    flush_interval_s: float = Field(
        0.5, gt=0, description="flush a partial chunk after this long [s]: the most a SIGKILL loses"
    )
    max_bytes: int | None = Field(None, description="rotate past this file size [bytes] (None: never)")
    max_duration_s: float | None = Field(None, description="rotate past this file age [s] (None: never)")
    compression: str = Field("zstd", description="chunk compression: zstd, lz4 or none")
    foxglove_scene: bool = Field(
        False, description="also write the Foxglove scene channels (scene/<robot>/...), in Foxglove's own schemas"
    )
    launch_file: str | None = Field(None, description="the launch file of this run, attached as launch.yaml")
    service_configs: dict[str, ServiceConfig] = Field(
        default_factory=dict,
        description="service name -> kind and settings file, recorded as each service's resolved settings "
        "(the launcher fills it in)",
    )


def _write_failure(path: str, reason: str, written: int, code: int | None = None) -> str:
    """The one error line of a recorder that cannot write; the cause by errno, not guessed."""
    causes = {
        errno.EEXIST: "the file exists and a recording never overwrites one: give a new name or folder",
        errno.EISDIR: "that is a folder: give a file name (gpmppi launch --record DIR picks one inside DIR)",
        errno.ENOENT: "its folder does not exist: create it first",
        errno.EACCES: "no permission to write there: give another path",
        errno.EROFS: "the file system is read-only: give another path",
        errno.ENOSPC: "the disk is full",
        errno.EDQUOT: "the disk quota is used up",
        errno.EFBIG: "a file-size limit was reached",
    }
    cause = causes.get(code or 0, "the disk is full or a file-size limit was reached" if written else "")
    cause = f": {cause}" if cause else ""
    kept = f" (the {written} messages written so far read back: gpmppi inspect {path})" if written else ""
    return f"cannot write {path}: {reason}{cause}; recording stopped{kept}"


def run(settings: Settings) -> int:
    # past a file-size limit (RLIMIT_FSIZE) the kernel's default is to kill the process with SIGXFSZ; ignored,
    # the write fails with EFBIG instead and is handled like a full disk
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    started_ns = time.time_ns()
    scene = FoxgloveSceneMapper() if settings.foxglove_scene else None
    scene_schemas: dict[str, tuple[str, str, bytes]] = {}

    def write_scene(key: str, payload: bytes, log_time_ns: int) -> None:
        """The scene of one recorded message (already validated) on its scene channels."""
        assert scene is not None and writer is not None
        if not scene_feeds(key):  # a key the scene does not draw (cmd, terrain weights, raw odometry): no decode
            return
        try:
            msg = decode(model_for_key(key), payload)
        except (KeyError, DecodeError):
            return
        for out in scene.map(key, msg, log_time_ns):
            if out.topic not in scene_schemas:
                s = schema_of(out.topic)
                scene_schemas[out.topic] = (s.name, s.encoding, bytes(s.data))
            writer.write_encoded(out.topic, scene_schemas[out.topic], "protobuf", out.data, log_time_ns, out.stamp_ns)

    failure = ""
    writer: McapWriter | None = None
    try:
        writer = McapWriter(
            settings.path,
            chunk_size=settings.chunk_size,
            flush_interval_s=settings.flush_interval_s,
            max_bytes=settings.max_bytes,
            max_duration_s=settings.max_duration_s,
            compression=settings.compression,
        )
    except OSError as exc:
        failure = _write_failure(settings.path, exc.strerror or str(exc), 0, exc.errno)
    # the run's metadata is resolved off the loop (the services' settings in a child process, since loading
    # them imports their modules), so recording starts at once; it is written when it is ready
    pool = ThreadPoolExecutor(1, thread_name_prefix="recorder-meta")
    meta: Future[RunRecord] | None = pool.submit(resolve_run_record, settings, started_ns)
    learned: list[Future[tuple[str, bytes, str] | str]] = []  # learned profiles being read, to attach
    try:
        with Node(settings) as node:
            assert node.session is not None
            sub = node.session.declare_subscriber(
                settings.key_expr, zenoh.handlers.FifoChannel(settings.queue_capacity)
            )
            node.log.info("recording %s to %s", settings.key_expr, settings.path)

            def failed(exc: OSError) -> None:
                nonlocal failure
                assert writer is not None
                failure = _write_failure(
                    settings.path, writer.failed or str(exc), writer.messages_written, writer.failed_errno or exc.errno
                )
                node.error(failure)  # the one error line
                with node.counters.lock:
                    node.counters.status = "failing"
                    node.counters.flags["writing"] = False

            if failure:
                node.error(failure)
                with node.counters.lock:
                    node.counters.status = "failing"
            node.counters.flags["writing"] = not failure

            def drain() -> int:
                n = quarantined = unwritten = 0
                while (sample := sub.try_recv()) is not None:
                    if sample.kind != zenoh.SampleKind.PUT:
                        continue
                    n += 1
                    if failure or writer is None:
                        unwritten += 1  # still taken off the queue: a failing recorder never blocks a sender
                        continue
                    payload = sample.payload.to_bytes()
                    now = time.time_ns()
                    try:
                        ok = writer.record(str(sample.key_expr), payload, now, settings.max_payload_bytes)
                        if ok and scene is not None:
                            write_scene(str(sample.key_expr), payload, now)
                    except OSError as exc:
                        failed(exc)
                        unwritten += 1
                        continue
                    quarantined += not ok and not str(sample.key_expr).endswith(REJECTED_SUFFIX)
                    if ok and str(sample.key_expr).endswith(MODEL_UPDATE_SUFFIX):  # a learned profile: attach it
                        learned.append(pool.submit(learned_attachment, payload))
                with node.counters.lock:
                    node.counters.received += n
                if quarantined:
                    node.counters.count("quarantined", quarantined)
                if unwritten:
                    node.counters.count("unwritten", unwritten)
                return n

            def write_metadata(record: RunRecord) -> None:
                for warning in record.warnings:
                    node.log.warning(warning)
                if writer is None or failure:
                    return
                try:
                    for name, data in record.metadata:
                        writer.add_metadata(name, data)
                    for name, data, media_type in record.attachments:
                        writer.add_attachment(name, data, media_type)
                except OSError as exc:
                    failed(exc)

            def write_learned(wait: bool) -> None:
                for f in [f for f in learned if wait or f.done()]:
                    learned.remove(f)
                    att = f.result()
                    if isinstance(att, str):
                        node.log.warning(att)
                    elif writer is not None and not failure:
                        try:
                            writer.add_attachment(*att)
                        except OSError as exc:
                            failed(exc)

            while node.ok():
                if drain():
                    node.cycle()
                if meta is not None and meta.done():
                    write_metadata(meta.result())
                    meta = None
                if learned:
                    write_learned(False)
                if writer is not None and not failure:
                    try:
                        writer.flush_if_due()  # a quiet stream still reaches the disk within flush_interval_s
                    except OSError as exc:
                        failed(exc)
                node.spin_once()
            drain()  # what arrived before the stop
            write_learned(True)
            if meta is not None:  # stopped soon after the start: the run's metadata still goes in
                try:
                    write_metadata(meta.result(timeout=10.0))
                except futures.TimeoutError:  # not the built-in TimeoutError before Python 3.11
                    node.log.warning("run metadata not resolved within 10 s of the stop; the file has none")
    finally:
        pool.shutdown(wait=False, cancel_futures=True)
        if writer is not None and not failure:
            writer.close()
        elif writer is not None:
            try:
                writer.close()
            except OSError:
                pass  # already reported; what reached the file reads back
    return 0
