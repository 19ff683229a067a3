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
from services.recording.mcap_io import REJECTED_SUFFIX
from services.recording.mcap_writer import McapWriter
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


class _Recording:
    """One recording's writer and what feeds it: the subscription's samples (`drain`), the Foxglove scene of each
    (`settings.foxglove_scene`), the run's metadata and the learned profiles' attachments, resolved off the loop. A
    write error stops the writing (`failure`, one error line) and never the draining."""

    def __init__(self, settings: Settings, node: Node, writer: McapWriter | None, failure: str,
                 pool: ThreadPoolExecutor) -> None:
        self.settings, self.node, self.writer, self.failure, self.pool = settings, node, writer, failure, pool
        self.scene = FoxgloveSceneMapper() if settings.foxglove_scene else None
        self.scene_schemas: dict[str, tuple[str, str, bytes]] = {}
        self.learned: list[Future[tuple[str, bytes, str] | str]] = []  # learned profiles being read, to attach
        assert node.session is not None
        self.sub = node.session.declare_subscriber(settings.key_expr,
                                                   zenoh.handlers.FifoChannel(settings.queue_capacity))
        node.log.info("recording %s to %s", settings.key_expr, settings.path)
        if failure:
            node.error(failure)
            with node.counters.lock:
                node.counters.status = "failing"
        node.counters.flags["writing"] = not failure

    @property
    def writing(self) -> bool:
        return self.writer is not None and not self.failure

    def failed(self, exc: OSError) -> None:
        """A write failed: say so once (the one error line), stop writing, keep draining."""
        w = self.writer
        assert w is not None
        self.failure = _write_failure(self.settings.path, w.failed or str(exc), w.messages_written,
                                      w.failed_errno or exc.errno)
        self.node.error(self.failure)
        with self.node.counters.lock:
            self.node.counters.status = "failing"
            self.node.counters.flags["writing"] = False

    def drain(self) -> int:
        """Record every sample waiting; the number taken off the queue."""
        n = quarantined = unwritten = 0
        while (sample := self.sub.try_recv()) is not None:
            if sample.kind != zenoh.SampleKind.PUT:
                continue
            n += 1
            if not self.writing:
                unwritten += 1  # still taken off the queue: a failing recorder never blocks a sender
                continue
            key, payload, now = str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()
            try:
                ok = self.writer.record(key, payload, now, self.settings.max_payload_bytes)
                if ok and self.scene is not None:
                    self.write_scene(key, payload, now)
            except OSError as exc:
                self.failed(exc)
                unwritten += 1
                continue
            quarantined += not ok and not key.endswith(REJECTED_SUFFIX)
            if ok and key.endswith(MODEL_UPDATE_SUFFIX):  # a learned profile: attach it
                self.learned.append(self.pool.submit(learned_attachment, payload))
        counters = self.node.counters
        with counters.lock:
            counters.received += n
        if quarantined:
            counters.count("quarantined", quarantined)
        if unwritten:
            counters.count("unwritten", unwritten)
        return n

    def write_scene(self, key: str, payload: bytes, log_time_ns: int) -> None:
        """The scene of one recorded message (already validated) on its scene channels."""
        assert self.scene is not None and self.writer is not None
        if not scene_feeds(key):  # a key the scene does not draw (cmd, terrain weights, raw odometry): no decode
            return
        try:
            msg = decode(model_for_key(key), payload)
        except (KeyError, DecodeError):
            return
        for out in self.scene.map(key, msg, log_time_ns):
            if out.topic not in self.scene_schemas:
                sch = schema_of(out.topic)
                self.scene_schemas[out.topic] = (sch.name, sch.encoding, bytes(sch.data))
            self.writer.write_encoded(out.topic, self.scene_schemas[out.topic], "protobuf", out.data, log_time_ns,
                                      out.stamp_ns)

    def write_metadata(self, record: RunRecord) -> None:
        for warning in record.warnings:
            self.node.log.warning(warning)
        if not self.writing:
            return
        try:
            for name, data in record.metadata:
                self.writer.add_metadata(name, data)
            for name, data, media_type in record.attachments:
                self.writer.add_attachment(name, data, media_type)
        except OSError as exc:
            self.failed(exc)

    def write_learned(self, wait: bool) -> None:
        """Attach the learned profiles read so far (`wait`: all of them)."""
        for f in [f for f in self.learned if wait or f.done()]:
            self.learned.remove(f)
            att = f.result()
            if isinstance(att, str):
                self.node.log.warning(att)
            elif self.writing:
                try:
                    self.writer.add_attachment(*att)
                except OSError as exc:
                    self.failed(exc)

    def flush_if_due(self) -> None:
        if self.writing:
            try:
                self.writer.flush_if_due()  # a quiet stream still reaches the disk within flush_interval_s
            except OSError as exc:
                self.failed(exc)


def _open_writer(settings: Settings) -> tuple[McapWriter | None, str]:
    """The file's writer, or None and the one error line why it cannot be written."""
    try:
        return McapWriter(settings.path, chunk_size=settings.chunk_size, flush_interval_s=settings.flush_interval_s,
                          max_bytes=settings.max_bytes, max_duration_s=settings.max_duration_s,
                          compression=settings.compression), ""
    except OSError as exc:
        return None, _write_failure(settings.path, exc.strerror or str(exc), 0, exc.errno)


def run(settings: Settings) -> int:
    # past a file-size limit (RLIMIT_FSIZE) the kernel's default is to kill the process with SIGXFSZ; ignored,
    # the write fails with EFBIG instead and is handled like a full disk
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    started_ns = time.time_ns()
    writer, failure = _open_writer(settings)
    # the run's metadata is resolved off the loop (the services' settings in a child process, since loading
    # them imports their modules), so recording starts at once; it is written when it is ready
    pool = ThreadPoolExecutor(1, thread_name_prefix="recorder-meta")
    meta: Future[RunRecord] | None = pool.submit(resolve_run_record, settings, started_ns)
    rec: _Recording | None = None
    try:
        with Node(settings) as node:
            rec = _Recording(settings, node, writer, failure, pool)
            while node.ok():
                if rec.drain():
                    node.cycle()
                if meta is not None and meta.done():
                    rec.write_metadata(meta.result())
                    meta = None
                if rec.learned:
                    rec.write_learned(False)
                rec.flush_if_due()
                node.spin_once()
            rec.drain()  # what arrived before the stop
            rec.write_learned(True)
            if meta is not None:  # stopped soon after the start: the run's metadata still goes in
                try:
                    rec.write_metadata(meta.result(timeout=10.0))
                except futures.TimeoutError:  # not the built-in TimeoutError before Python 3.11
                    node.log.warning("run metadata not resolved within 10 s of the stop; the file has none")
    finally:
        pool.shutdown(wait=False, cancel_futures=True)
        failure = rec.failure if rec is not None else failure
        if writer is not None and not failure:
            writer.close()
        elif writer is not None:
            try:
                writer.close()
            except OSError:
                pass  # already reported; what reached the file reads back
    return 0
