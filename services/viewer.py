"""viewer: streams states, plans, the task and health to rerun (spawned viewer, an .rrd file, or a gRPC URL).

The mapping lives in `services.view.rerun_map` (shared with the offline converter, `gpmppi replay --rerun`).

Newest-wins: the viewer never slows the control path. Its subscription's callback only appends to a bounded
ring (`queue` samples; when the viewer falls behind, the oldest waiting samples are dropped and counted as
`dropped`), so it never blocks Zenoh's receive thread and never back-pressures the router. The control path's
publishers use Zenoh's default congestion control for data (drop), so a viewer that is stopped outright
(SIGSTOP, a hung GUI) has its queue at the router dropped instead of delaying anyone; after the session lease
runs out the router closes the stopped session.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from pathlib import Path
from typing import Literal

import zenoh
from pydantic import Field

from schemas import DecodeError, decode, model_for_key
from services.recording.output_files import create_exclusive
from services.runtime.node import Node
from services.runtime.node_settings import NodeSettings
from services.view.rerun_map import RerunMapper, ViewOptions
from services.view.rerun_stream import open_stream


class Settings(NodeSettings):
    service: str = Field("viewer", description="service name")
    mode: Literal["spawn", "save", "connect", "serve", "off"] = Field("save", description="where the rerun stream goes")
    path: str = Field("runs/view.rrd", description="output file for mode 'save'")
    url: str = Field("rerun+http://127.0.0.1:9876/proxy", description="viewer gRPC URL for mode 'connect'")
    serve_port: int = Field(9876, gt=0, lt=65536, description="gRPC port for mode 'serve' (on this machine)")
    key_expr: str = Field("gpmppi/**", description="what to show")
    queue: int = Field(
        4000, gt=0, description="samples waiting for the viewer at most; beyond, the oldest are dropped (counted)"
    )
    flush_s: float = Field(
        0.25, gt=0, description="live modes: data is sent to rerun in chunks (time series in columns) this often [s]"
    )
    save_flush_s: float = Field(
        2.0, gt=0, description="mode 'save': the same for a file, where no one waits and bigger chunks are smaller [s]"
    )
    samples_every: int = Field(2, ge=1, description="draw the rollouts of every n-th plan")
    max_samples: int = Field(32, ge=0, description="draw at most this many rollouts of a plan")
    sample_stride: int = Field(2, ge=1, description="draw every n-th point along a rollout")
    ellipse_every: int = Field(8, ge=1, description="draw every n-th covariance ellipse of the plan")
    path_chunk: int = Field(50, ge=2, description="driven-path states per strip (the path grows by strips)")
    timing_warmup_plans: int = Field(
        5, ge=0, description="a (re)started planner's first plans are an event, not plotted (start-up spike)"
    )

    def options(self) -> ViewOptions:
        return ViewOptions(
            samples_every=self.samples_every,
            max_samples=self.max_samples,
            sample_stride=self.sample_stride,
            ellipse_every=self.ellipse_every,
            path_chunk=self.path_chunk,
            timing_warmup_plans=self.timing_warmup_plans,
        )


class Ring:
    """Newest-wins buffer filled by a Zenoh callback: appending never blocks; when full, the oldest is dropped."""

    def __init__(self, capacity: int) -> None:
        self._items: deque[zenoh.Sample] = deque(maxlen=capacity)
        self.dropped = 0

    def push(self, sample: zenoh.Sample) -> None:
        if len(self._items) == self._items.maxlen:
            self.dropped += 1
        self._items.append(sample)  # deque.append is atomic under the GIL; maxlen drops the oldest

    def pop(self) -> zenoh.Sample | None:
        try:
            return self._items.popleft()
        except IndexError:
            return None


def run(settings: Settings) -> int:
    rec = None
    flush_s = settings.save_flush_s if settings.mode == "save" else settings.flush_s
    if settings.mode == "save":
        # the viewer never overwrites a file (an earlier run's .rrd): it claims its own exclusively first
        try:
            Path(settings.path).parent.mkdir(parents=True, exist_ok=True)
            create_exclusive(settings.path)
        except OSError as exc:
            logging.getLogger(f"gpmppi.{settings.service}").error(
                "cannot save the rerun stream to %s: %s; a view is never written over an existing file: give "
                "a new name or folder", settings.path, exc.strerror or exc,
            )
            return 2
    if settings.mode != "off":
        target = settings.path if settings.mode == "save" else settings.url if settings.mode == "connect" else None
        rec = open_stream(settings.mode, target, settings.serve_port, batch_s=flush_s)
    mapper = RerunMapper(rec, settings.options()) if rec is not None else None
    try:
        with Node(settings) as node:
            assert node.session is not None
            ring = Ring(settings.queue)
            sub = node.session.declare_subscriber(settings.key_expr, zenoh.handlers.Callback(ring.push))
            next_flush = time.monotonic() + flush_s
            reported_drops, last_drop = 0, 0.0
            while node.ok():
                handled = 0
                while handled < 2000 and (sample := ring.pop()) is not None:
                    key = str(sample.key_expr)
                    try:
                        msg = decode(model_for_key(key), sample.payload.to_bytes(), settings.max_payload_bytes)
                    except (KeyError, DecodeError) as exc:
                        node.reject(f"{key}: {exc}")
                        continue
                    with node.counters.lock:
                        node.counters.received += 1
                    if mapper is not None:
                        mapper.log(key, msg, time.time_ns())
                    handled += 1
                if ring.dropped != reported_drops:
                    node.counters.count("dropped", ring.dropped - reported_drops)
                    node.counters.status = "degraded"  # the view has gaps; ok again after 10 s without drops
                    reported_drops, last_drop = ring.dropped, time.monotonic()
                elif node.counters.status == "degraded" and time.monotonic() - last_drop > 10.0:
                    node.counters.status = "ok"
                if handled:
                    node.cycle()
                if mapper is not None and time.monotonic() >= next_flush:
                    mapper.flush()
                    next_flush = time.monotonic() + flush_s
                node.spin_once(0.02)
            sub.undeclare()
    finally:
        if mapper is not None:
            mapper.flush()
        if rec is not None:
            rec.flush()
            rec.disconnect()
    return 0
