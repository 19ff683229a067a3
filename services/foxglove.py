"""foxglove: serves the running stack to Foxglove (foxglove-sdk's WebSocket server, protocol `foxglove.websocket.v1`).

- Every `gpmppi/**` key is a channel of its own, JSON with the JSON Schema of its pydantic model (as in the MCAP
  recording); the payload goes out as it was received, once it has decoded.
- What nobody reads costs no decode: a message is decoded and mapped only when a client is subscribed to its key's
  channel or to a scene topic it feeds (`scene_feeds`), and only the scene topics read are made; the rest is counted
  `unread`. The plan's scene is drawn at most `plan_hz` times a second.
- The 3D scene (robot pose and frame transforms, lane and tightened bounds, obstacles and their inflation, plan and
  covariance ellipses, rollouts coloured by cost) goes on `scene/<robot>/...` in Foxglove's own schemas, from the
  one mapping `services.view.foxglove_scene` (shared with the recorder's scene channels and `gpmppi replay`).

The control path comes first. The subscription's callback keeps only the newest sample of each key (a ring of one
per key: a key that arrives again before it was handled replaces the waiting one, counted as `dropped`), so it never
blocks Zenoh's receive thread, and the service falls behind by at most one sample per key. The server keeps at most
`backlog` messages per client and drops the oldest for a slow client; a client that stops reading never holds the
service up. The server listens on loopback unless `host` says otherwise (see docs/foxglove.md for a secured stack).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import Any

import zenoh
from pydantic import Field

from schemas import KEYS, DecodeError, decode, model_for_key
from services.recording.mcap_io import schema_name
from services.runtime.node import Node
from services.runtime.node_settings import NodeSettings
from services.view.foxglove_scene import (
    FoxgloveSceneMapper,
    SceneOptions,
    robot_of,
    scene_feeds,
    scene_topic,
    scene_topics,
    schema_of,
)


class Settings(NodeSettings):
    service: str = Field("foxglove", description="service name")
    host: str = Field(
        "127.0.0.1", description="address the WebSocket server listens on (loopback: reach it through an SSH tunnel)"
    )
    port: int = Field(8765, ge=0, lt=65536, description="WebSocket port (0: any free port, printed at the start)")
    key_expr: str = Field("gpmppi/**", description="what to serve")
    backlog: int = Field(
        256, gt=0, description="messages waiting for one client at most; beyond, the oldest are dropped for it"
    )
    plan_hz: float = Field(
        5.0, ge=0.0, description="draw the plan's scene (nominal, ellipses, bounds, rollouts) at most this often [Hz]; "
        "0: every plan"
    )
    samples_every: int = Field(1, ge=1, description="draw the rollouts of every n-th plan drawn")
    max_samples: int = Field(32, ge=0, description="draw at most this many rollouts of a plan")
    sample_stride: int = Field(2, ge=1, description="draw every n-th point along a rollout")
    ellipse_every: int = Field(8, ge=1, description="draw every n-th covariance ellipse of the plan")
    path_chunk: int = Field(50, ge=2, description="driven-path states per strip (the path grows by strips)")

    def options(self) -> SceneOptions:
        return SceneOptions(
            plan_hz=self.plan_hz,
            samples_every=self.samples_every,
            max_samples=self.max_samples,
            sample_stride=self.sample_stride,
            ellipse_every=self.ellipse_every,
            path_chunk=self.path_chunk,
        )


class Newest:
    """The newest sample of each key, filled by a Zenoh callback: a key that arrives again before it was taken
    replaces the waiting sample (a ring of one per key, counted in `dropped`); putting never waits on the reader."""

    def __init__(self) -> None:
        self._lock = threading.Lock()  # held for a dict assignment or swap only
        self._waiting: dict[str, zenoh.Sample] = {}
        self.dropped = 0

    def push(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        with self._lock:
            if key in self._waiting:
                self.dropped += 1
            self._waiting[key] = sample

    def take(self) -> list[zenoh.Sample]:
        with self._lock:
            waiting, self._waiting = self._waiting, {}
        return list(waiting.values())


class Route:
    """Where one key's messages go: its own JSON channel and the scene channels its messages feed (by name)."""

    def __init__(self, channel: Any, feeds: list[tuple[str, Any]]) -> None:
        self.channel = channel
        self.feeds = feeds

    def readers(self) -> tuple[bool, list[str]]:
        """Whether a client reads the key's own channel, and the scene topics (names) it feeds that a client
        reads (foxglove-sdk counts a channel's subscribers: `has_sinks`)."""
        return self.channel.has_sinks(), [name for name, channel in self.feeds if channel.has_sinks()]


class Channels:
    """The server's channels, created on first use: `gpmppi/**` keys as JSON with their JSON Schema, scene topics
    in Foxglove's protobuf schemas."""

    def __init__(self, context: object) -> None:
        self.context = context
        self._channels: dict[str, object] = {}
        self._routes: dict[str, Route] = {}

    def route(self, key: str) -> Route:
        """The key's route (KeyError: no message is registered for the key)."""
        route = self._routes.get(key)
        if route is None:
            robot = robot_of(key)
            feeds = [(name, self.scene(scene_topic(robot, name))) for name in sorted(scene_feeds(key))]
            route = self._routes[key] = Route(self.json(key), feeds)
        return route

    def json(self, key: str) -> object:
        channel = self._channels.get(key)
        if channel is None:
            import foxglove

            model = model_for_key(key)
            schema = foxglove.Schema(
                name=schema_name(model), encoding="jsonschema", data=json.dumps(model.model_json_schema()).encode()
            )
            channel = foxglove.Channel(key, schema=schema, message_encoding="json", context=self.context)
            self._channels[key] = channel
        return channel

    def scene(self, topic: str) -> object:
        channel = self._channels.get(topic)
        if channel is None:
            import foxglove

            channel = foxglove.Channel(
                topic, schema=schema_of(topic), message_encoding="protobuf", context=self.context
            )
            self._channels[topic] = channel
        return channel


def run(settings: Settings) -> int:
    import foxglove

    log = logging.getLogger(f"gpmppi.{settings.service}")
    context = foxglove.Context()
    channels = Channels(context)
    # the robot's fixed keys and its scene are advertised from the start, so a layout finds its topics at once
    for template, _ in KEYS.values():
        if "{service}" not in template:
            channels.json(template.format(robot=settings.robot))
    for topic in scene_topics(settings.robot):
        channels.scene(topic)
    try:
        server = foxglove.start_server(
            name=f"gpmppi {settings.robot}",
            host=settings.host,
            port=settings.port,
            context=context,
            message_backlog_size=settings.backlog,
        )
    except Exception as exc:  # noqa: BLE001 - the SDK raises its own error types for a port in use, a bad address
        log.error(
            "cannot serve Foxglove on %s:%d: %s; give another --foxglove HOST:PORT", settings.host, settings.port, exc
        )
        return 2
    print(f"foxglove: serving ws://{settings.host}:{server.port} (open it in Foxglove: Open connection)", flush=True)
    mapper = FoxgloveSceneMapper(settings.options())
    try:
        with Node(settings) as node:
            assert node.session is not None
            newest = Newest()
            sub = node.session.declare_subscriber(settings.key_expr, zenoh.handlers.Callback(newest.push))
            reported = 0
            node.counters.flags["serving"] = True
            while node.ok():
                handled = unread = 0
                for sample in newest.take():
                    key = str(sample.key_expr)
                    try:
                        route = channels.route(key)
                    except KeyError as exc:
                        node.reject(f"{key}: {exc}")
                        continue
                    # what nobody reads costs no decode: neither the key's own channel nor a scene topic it feeds
                    # has a subscribed client
                    forward, wanted = route.readers()
                    handled += 1
                    if not forward and not wanted:
                        unread += 1
                        continue
                    payload = sample.payload.to_bytes()
                    try:
                        msg = decode(model_for_key(key), payload, settings.max_payload_bytes)
                    except DecodeError as exc:
                        node.reject(f"{key}: {exc}")
                        continue
                    now = time.time_ns()
                    if forward:
                        route.channel.log(payload, log_time=now)
                    # each scene message is encoded once here; the server sends the same bytes to every client
                    for scene in mapper.map(key, msg, now, wanted) if wanted else ():
                        channels.scene(scene.topic).log(scene.data, log_time=now)  # type: ignore[attr-defined]
                if handled:
                    with node.counters.lock:
                        node.counters.received += handled
                    if unread:  # received, and dropped unread: no client reads what they feed
                        node.counters.count("unread", unread)
                    node.cycle()
                if newest.dropped != reported:
                    node.counters.count("dropped", newest.dropped - reported)
                    reported = newest.dropped
                node.spin_once(0.02)
            sub.undeclare()
    finally:
        server.stop()
    return 0
