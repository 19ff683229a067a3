"""ingress: turns an odometry source into `State` on `gpmppi/{robot}/state`.

Sources: the simulator's `odom/raw` (JSON State), or ROS 2 `nav_msgs/msg/Odometry` as CDR over Zenoh
(rmw_zenoh key or zenoh-bridge-ros2dds key). Stale, non-finite or malformed input is rejected and counted.
"""

from __future__ import annotations

import time
from typing import Literal

import numpy as np
import zenoh
from pydantic import BaseModel, ConfigDict, Field

from schemas import State
from services.codec import ros2
from services.codec.convert import state_from_array, state_to_array
from services.runtime.node import Node
from services.runtime.node_settings import NodeSettings
from services.runtime.scheduling import Inbox


class Ros2Source(BaseModel):
    model_config = ConfigDict(extra="forbid")

    topic: str = Field("odom", description="ROS 2 odometry topic (relative to namespace)")
    namespace: str = Field("", description="ROS 2 namespace, e.g. /jackal")
    domain_id: int = Field(0, ge=0, description="ROS_DOMAIN_ID (rmw_zenoh key prefix)")
    key_style: ros2.KeyStyle = Field("rmw_zenoh", description="rmw_zenoh key or zenoh-bridge-ros2dds key")
    distro: ros2.Distro = Field("jazzy", description="message definitions (and type hash) of this ROS 2 distro")
    key: str | None = Field(None, description="explicit Zenoh key (overrides the fields above)")

    def key_expr(self) -> str:
        if self.key:
            return self.key
        # the hash is wildcarded so a publisher of another distro's hash still matches
        return ros2.topic_key(
            self.topic,
            "nav_msgs/msg/Odometry",
            self.namespace,
            self.domain_id,
            self.key_style,
            self.distro,
            hash_wildcard=True,
        )


class Settings(NodeSettings):
    service: str = Field("ingress", description="service name")
    source: Literal["sim", "ros2"] = Field("sim", description="where odometry comes from")
    ros2: Ros2Source = Field(default_factory=Ros2Source, description="ROS 2 odometry source")
    max_age_s: float | None = Field(
        0.5, description="reject input whose stamp is older than this [s] (None: no check, e.g. bag replay)"
    )
    max_future_s: float = Field(0.2, ge=0, description="reject input stamped this far in the future [s]")
    frame_id: str | None = Field(None, description="frame to publish in (None: keep the source's)")
    max_speed: float = Field(10.0, gt=0, description="reject |v| above this as implausible [m/s]")
    max_yaw_rate: float = Field(20.0, gt=0, description="reject |omega| above this as implausible [rad/s]")


class Ingress:
    """Validation shared by both sources (kept apart from Zenoh so it is easy to reason about)."""

    def __init__(self, settings: Settings, node: Node) -> None:
        self.settings = settings
        self.node = node
        self.last_stamp = -1

    def check(self, stamp_ns: int, x: np.ndarray, now_ns: int) -> str | None:
        s = self.settings
        if not np.all(np.isfinite(x)):
            return f"non-finite state {x.tolist()}"
        if abs(x[3]) > s.max_speed or abs(x[4]) > s.max_yaw_rate:
            return f"implausible velocity v={x[3]:.3g} omega={x[4]:.3g} (limits {s.max_speed}, {s.max_yaw_rate})"
        if s.max_age_s is not None and (now_ns - stamp_ns) > s.max_age_s * 1e9:
            return f"stale: stamp is {(now_ns - stamp_ns) / 1e9:.3f} s old (limit {s.max_age_s} s)"
        if stamp_ns - now_ns > s.max_future_s * 1e9:
            return f"stamp {(stamp_ns - now_ns) / 1e9:.3f} s in the future (clock skew?)"
        if stamp_ns <= self.last_stamp:
            return f"stamp {stamp_ns} is not newer than the previous one {self.last_stamp}"
        return None

    def accept(self, stamp_ns: int, frame_id: str, x: np.ndarray, cov: np.ndarray | None) -> State | None:
        reason = self.check(stamp_ns, x, time.time_ns())
        if reason is not None:
            self.node.reject(reason)
            return None
        self.last_stamp = stamp_ns
        try:
            return state_from_array(x, stamp_ns, self.settings.frame_id or frame_id, cov)
        except ValueError as exc:
            self.node.reject(str(exc))
            return None


def ros2_odometry_inbox(node: Node, settings: Settings) -> Inbox:
    """ROS 2 odometry on its key, newest only: the loop decodes the newest message; one that a newer one replaced
    before the loop took it is decoded on Zenoh's thread, so that a bad message is counted and logged whatever the
    loop's timing (as `TypedSubscription` does for our own messages)."""
    distro = settings.ros2.distro

    def check_replaced(sample: zenoh.Sample) -> None:
        with node.counters.lock:
            node.counters.received += 1
        try:
            ros2.odometry_from_cdr(sample.payload.to_bytes(), distro)
        except ValueError as exc:
            node.reject(f"{sample.key_expr}: {exc}")

    return node.inbox(settings.ros2.key_expr(), on_displaced=check_replaced)


def run(settings: Settings) -> int:
    with Node(settings) as node:
        out = node.publisher("state")
        ingress = Ingress(settings, node)
        if settings.source == "sim":
            odom = node.subscribe("odom_raw")
            raw = None
        else:
            odom = None
            raw = ros2_odometry_inbox(node, settings)
            node.log.info("ROS 2 odometry from %s", settings.ros2.key_expr())
        while node.ok():
            state: State | None = None
            if odom is not None:
                msg = odom.take()
                if msg is not None:
                    cov = None if msg.covariance is None else np.asarray(msg.covariance).reshape(5, 5)
                    state = ingress.accept(msg.header.stamp_ns, msg.header.frame_id, state_to_array(msg), cov)
            elif raw is not None and (sample := raw.take()) is not None:
                with node.counters.lock:  # replaced samples are counted on Zenoh's thread
                    node.counters.received += 1
                try:
                    reading = ros2.odometry_from_cdr(sample.payload.to_bytes(), settings.ros2.distro)
                    state = ingress.accept(reading.stamp_ns, reading.frame_id, reading.state, reading.covariance)
                except ValueError as exc:
                    node.reject(f"{sample.key_expr}: {exc}")
            if state is not None:
                out.put(state)
                node.cycle()
                continue  # look for the next input right away
            node.spin_once()
    return 0
