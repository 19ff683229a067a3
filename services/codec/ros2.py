"""ROS 2 over Zenoh without ROS: CDR (de)serialization with rosbags, rmw_zenoh key expressions and attachments.

rmw_zenoh publishes a topic on `<domain_id>/<fully qualified topic without leading slash>/<DDS type name>/<type hash>`,
e.g. `0/jackal/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_9c45...`, with an attachment serialized in the
Zenoh serialization format: "sequence_number" int64, "source_timestamp" int64 [ns], "source_gid" 16 bytes.
(Humble's rmw_zenoh has no type hashes and uses `TypeHashNotSupported`.) zenoh-bridge-ros2dds publishes
plain `<namespace>/<topic>` keys with the same CDR payload and no attachment.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Literal

import numpy as np
from rosbags.typesys import Stores, get_typestore
from zenoh import ZBytes
from zenoh.ext import Int64, z_deserialize, z_serialize

from services.codec.convert import yaw_from_quaternion

TYPE_HASH_UNSUPPORTED = "TypeHashNotSupported"
GID_SIZE = 16

KeyStyle = Literal["rmw_zenoh", "bridge"]
Distro = Literal["humble", "jazzy"]


@lru_cache(maxsize=4)
def typestore(distro: Distro = "jazzy") -> Any:
    return get_typestore(Stores.ROS2_HUMBLE if distro == "humble" else Stores.ROS2_JAZZY)


def dds_type_name(ros_type: str) -> str:
    """'geometry_msgs/msg/Twist' -> 'geometry_msgs::msg::dds_::Twist_' (the name rmw_zenoh puts in keys)."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def type_hash(ros_type: str, distro: Distro = "jazzy") -> str:
    """The RIHS01 type-description hash (jazzy and later) or Humble's placeholder."""
    if distro == "humble":
        return TYPE_HASH_UNSUPPORTED
    return typestore(distro).hash_rihs01(ros_type)


def _strip(name: str) -> str:
    return "/".join(part for part in name.split("/") if part)


def topic_key(
    topic: str,
    ros_type: str,
    namespace: str = "",
    domain_id: int = 0,
    style: KeyStyle = "rmw_zenoh",
    distro: Distro = "jazzy",
    hash_wildcard: bool = False,
) -> str:
    """The Zenoh key a ROS 2 topic travels on (rmw_zenoh or zenoh-bridge-ros2dds style)."""
    fq_topic = _strip(f"{namespace}/{topic}")
    if not fq_topic:
        raise ValueError(f"empty ROS topic name (namespace={namespace!r}, topic={topic!r})")
    if style == "bridge":
        return fq_topic
    hash_part = "*" if hash_wildcard else type_hash(ros_type, distro)
    return f"{domain_id}/{fq_topic}/{dds_type_name(ros_type)}/{hash_part}"


@dataclass
class Attachment:
    sequence_number: int
    source_timestamp: int
    source_gid: bytes

    def to_bytes(self) -> bytes:
        if len(self.source_gid) != GID_SIZE:
            raise ValueError(f"source_gid must be {GID_SIZE} bytes, got {len(self.source_gid)}")
        return z_serialize(
            (
                "sequence_number",
                Int64(self.sequence_number),
                "source_timestamp",
                Int64(self.source_timestamp),
                "source_gid",
                bytes(self.source_gid),
            )
        ).to_bytes()

    @classmethod
    def from_bytes(cls, data: bytes) -> Attachment:
        parts = z_deserialize(tuple[str, Int64, str, Int64, str, bytes], ZBytes(data))  # type: ignore[arg-type]
        if (parts[0], parts[2], parts[4]) != ("sequence_number", "source_timestamp", "source_gid"):
            raise ValueError(f"not an rmw_zenoh attachment: keys {parts[0]!r}, {parts[2]!r}, {parts[4]!r}")
        return cls(int(parts[1]), int(parts[3]), bytes(parts[5]))


def new_gid(seed: int | None = None) -> bytes:
    """A 16-byte publisher id (random unless seeded)."""
    if seed is None:
        return os.urandom(GID_SIZE)
    return np.random.default_rng(seed).integers(0, 256, GID_SIZE, dtype=np.uint8).tobytes()


# ---- messages ---------------------------------------------------------------------------------
def twist_cdr(
    v: float,
    omega: float,
    stamped: bool,
    frame_id: str = "base_link",
    stamp_ns: int | None = None,
    distro: Distro = "jazzy",
) -> bytes:
    """CDR bytes of geometry_msgs/msg/Twist or TwistStamped with linear.x = v, angular.z = omega."""
    ts = typestore(distro)
    vector3 = ts.types["geometry_msgs/msg/Vector3"]
    twist = ts.types["geometry_msgs/msg/Twist"](
        linear=vector3(float(v), 0.0, 0.0), angular=vector3(0.0, 0.0, float(omega))
    )
    if not stamped:
        return bytes(ts.serialize_cdr(twist, "geometry_msgs/msg/Twist"))
    stamp_ns = time.time_ns() if stamp_ns is None else stamp_ns
    header = ts.types["std_msgs/msg/Header"](
        stamp=ts.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000),
        frame_id=frame_id,
    )
    msg = ts.types["geometry_msgs/msg/TwistStamped"](header=header, twist=twist)
    return bytes(ts.serialize_cdr(msg, "geometry_msgs/msg/TwistStamped"))


@dataclass
class OdometryReading:
    stamp_ns: int
    frame_id: str
    state: np.ndarray  # [X, Y, yaw, v, omega], body-frame velocities
    covariance: np.ndarray | None  # (5, 5) over [X, Y, yaw, v, omega], None if unknown (all zeros)


# indices of [x, y, yaw] in the 6x6 pose covariance and [vx, wz] in the 6x6 twist covariance (x y z rx ry rz)
_POSE_IDX = [0, 1, 5]
_TWIST_IDX = [0, 5]


def odometry_from_cdr(data: bytes, distro: Distro = "jazzy") -> OdometryReading:
    """Decode nav_msgs/msg/Odometry CDR bytes; raises ValueError naming what was wrong."""
    try:
        msg = typestore(distro).deserialize_cdr(data, "nav_msgs/msg/Odometry")
    except Exception as exc:  # noqa: BLE001 - rosbags raises several types on malformed CDR
        raise ValueError(f"not a nav_msgs/msg/Odometry CDR payload ({type(exc).__name__}: {exc})") from exc
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    state = np.array([p.x, p.y, yaw_from_quaternion(q.x, q.y, q.z, q.w), lin.x, ang.z], dtype=np.float64)
    pose_cov = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)
    twist_cov = np.asarray(msg.twist.covariance, dtype=np.float64).reshape(6, 6)
    cov: np.ndarray | None = np.zeros((5, 5))
    cov[:3, :3] = pose_cov[np.ix_(_POSE_IDX, _POSE_IDX)]
    cov[3:, 3:] = twist_cov[np.ix_(_TWIST_IDX, _TWIST_IDX)]
    if not np.any(cov):
        cov = None
    sec, nanosec = int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)
    if sec < 0 or not 0 <= nanosec < 1_000_000_000:
        raise ValueError(f"nav_msgs/msg/Odometry stamp {sec} s {nanosec} ns is not a time since the epoch")
    stamp_ns = sec * 1_000_000_000 + nanosec
    return OdometryReading(stamp_ns, msg.header.frame_id or "odom", state, cov)


def odometry_cdr(
    state: np.ndarray,
    stamp_ns: int,
    frame_id: str = "odom",
    child_frame_id: str = "base_link",
    distro: Distro = "jazzy",
) -> bytes:
    """CDR bytes of a nav_msgs/msg/Odometry for [X, Y, yaw, v, omega] (for tests and replay tools)."""
    ts = typestore(distro)
    t = ts.types
    x, y, yaw, v, omega = (float(s) for s in state)
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000),
        frame_id=frame_id,
    )
    pose = t["geometry_msgs/msg/PoseWithCovariance"](
        pose=t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x, y, 0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](0.0, 0.0, float(np.sin(yaw / 2)), float(np.cos(yaw / 2))),
        ),
        covariance=np.zeros(36),
    )
    vec = t["geometry_msgs/msg/Vector3"]
    twist = t["geometry_msgs/msg/TwistWithCovariance"](
        twist=t["geometry_msgs/msg/Twist"](linear=vec(v, 0.0, 0.0), angular=vec(0.0, 0.0, omega)),
        covariance=np.zeros(36),
    )
    msg = t["nav_msgs/msg/Odometry"](header=header, child_frame_id=child_frame_id, pose=pose, twist=twist)
    return bytes(ts.serialize_cdr(msg, "nav_msgs/msg/Odometry"))


# ---- navigation: nav_msgs/Path and geometry_msgs/PoseStamped in, the plan out as nav_msgs/Path -------------------
# (kept together at the end of the file: other message kinds go in their own sections)
@dataclass
class PathReading:
    """A decoded nav_msgs/msg/Path: its header and the (x, y) of each pose, in order."""

    stamp_ns: int
    frame_id: str
    points: np.ndarray  # (P, 2) [m], possibly empty or non-finite: the caller checks


@dataclass
class PoseReading:
    """A decoded geometry_msgs/msg/PoseStamped: its header, position and yaw."""

    stamp_ns: int
    frame_id: str
    position: np.ndarray  # (2,) [m], possibly non-finite: the caller checks
    yaw: float  # [rad]


def _stamp_ns(header: Any, ros_type: str) -> int:
    sec, nanosec = int(header.stamp.sec), int(header.stamp.nanosec)
    if sec < 0 or not 0 <= nanosec < 1_000_000_000:
        raise ValueError(f"{ros_type} stamp {sec} s {nanosec} ns is not a time since the epoch")
    return sec * 1_000_000_000 + nanosec


def _deserialize(data: bytes, ros_type: str, distro: Distro) -> Any:
    try:
        return typestore(distro).deserialize_cdr(data, ros_type)
    except Exception as exc:  # noqa: BLE001 - rosbags raises several types on malformed CDR
        raise ValueError(f"not a {ros_type} CDR payload ({type(exc).__name__}: {exc})") from exc


def path_from_cdr(data: bytes, distro: Distro = "jazzy") -> PathReading:
    """Decode nav_msgs/msg/Path CDR bytes; raises ValueError naming what was wrong (the points are not checked)."""
    msg = _deserialize(data, "nav_msgs/msg/Path", distro)
    points = np.array([[p.pose.position.x, p.pose.position.y] for p in msg.poses], dtype=np.float64).reshape(-1, 2)
    return PathReading(_stamp_ns(msg.header, "nav_msgs/msg/Path"), msg.header.frame_id, points)


def pose_stamped_from_cdr(data: bytes, distro: Distro = "jazzy") -> PoseReading:
    """Decode geometry_msgs/msg/PoseStamped CDR bytes; raises ValueError naming what was wrong."""
    msg = _deserialize(data, "geometry_msgs/msg/PoseStamped", distro)
    p, q = msg.pose.position, msg.pose.orientation
    yaw = yaw_from_quaternion(q.x, q.y, q.z, q.w)
    return PoseReading(_stamp_ns(msg.header, "geometry_msgs/msg/PoseStamped"), msg.header.frame_id,
                       np.array([p.x, p.y], dtype=np.float64), yaw)


def path_cdr(poses: np.ndarray, stamps_ns: np.ndarray, frame_id: str, stamp_ns: int,
             distro: Distro = "jazzy") -> bytes:
    """CDR bytes of a nav_msgs/msg/Path through `poses` (K, 3) = [x, y, yaw] [m, rad], pose k stamped
    `stamps_ns[k]`, the path's header `stamp_ns`, everything in `frame_id`."""
    ts = typestore(distro)
    t = ts.types
    time_type, header_type = t["builtin_interfaces/msg/Time"], t["std_msgs/msg/Header"]
    point, quaternion = t["geometry_msgs/msg/Point"], t["geometry_msgs/msg/Quaternion"]
    pose, stamped = t["geometry_msgs/msg/Pose"], t["geometry_msgs/msg/PoseStamped"]

    def header(ns: int) -> Any:
        return header_type(stamp=time_type(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame_id)

    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    half = 0.5 * p[:, 2]
    qz, qw = np.sin(half), np.cos(half)
    items = [
        stamped(header=header(int(s)), pose=pose(position=point(float(x), float(y), 0.0),
                                                 orientation=quaternion(0.0, 0.0, float(z), float(w))))
        for (x, y, _), s, z, w in zip(p, np.asarray(stamps_ns, dtype=np.int64), qz, qw, strict=True)
    ]
    msg = t["nav_msgs/msg/Path"](header=header(int(stamp_ns)), poses=items)
    return bytes(ts.serialize_cdr(msg, "nav_msgs/msg/Path"))


# ---- nav_msgs/OccupancyGrid -----------------------------------------------------------------
def occupancy_grid_from_cdr(data: bytes, distro: Distro = "jazzy", lethal: int = 100) -> Any:  # noqa: ANN401
    """Our OccupancyGrid from nav_msgs/msg/OccupancyGrid CDR bytes (values as nav_msgs' int8: -1 unknown; `lethal`
    the threshold of obstacles); a ValueError naming what was wrong (not that type, a size that does not match the
    data, a non-finite pose, a bad stamp)."""
    from schemas import Header, OccupancyGrid

    try:
        msg = typestore(distro).deserialize_cdr(data, "nav_msgs/msg/OccupancyGrid")
    except Exception as exc:  # noqa: BLE001 - rosbags raises several types on malformed CDR
        raise ValueError(f"not a nav_msgs/msg/OccupancyGrid CDR payload ({type(exc).__name__}: {exc})") from exc
    info = msg.info
    w, h, n = int(info.width), int(info.height), len(msg.data)
    if w * h != n or n == 0:
        raise ValueError(f"nav_msgs/msg/OccupancyGrid of width {w} x height {h} carries {n} values; the grid's "
                         "size must match its data")
    p, q = info.origin.position, info.origin.orientation
    pose = (float(p.x), float(p.y), yaw_from_quaternion(q.x, q.y, q.z, q.w), float(info.resolution))
    if not all(np.isfinite(pose)) or pose[3] <= 0:
        raise ValueError(f"nav_msgs/msg/OccupancyGrid origin {pose[:3]} / resolution {pose[3]} must be finite, the "
                         "resolution > 0")
    sec, nanosec = int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)
    if sec < 0 or not 0 <= nanosec < 1_000_000_000:
        raise ValueError(f"nav_msgs/msg/OccupancyGrid stamp {sec} s {nanosec} ns is not a time since the epoch")
    header = Header(stamp_ns=sec * 1_000_000_000 + nanosec, frame_id=msg.header.frame_id or "map")
    values = np.asarray(msg.data, dtype=np.int8).astype(np.int64)
    # built without validating each of the cells again (rosbags gives int8: in range by type)
    return OccupancyGrid.model_construct(
        header=header, resolution=pose[3], width=w, height=h, origin_x=pose[0], origin_y=pose[1],
        origin_yaw=pose[2], lethal=int(lethal), data=values.tolist())


def occupancy_grid_cdr(
    values: np.ndarray, resolution: float, origin: tuple[float, float, float], stamp_ns: int,
    frame_id: str = "odom", distro: Distro = "jazzy", width: int | None = None, height: int | None = None,
) -> bytes:
    """CDR bytes of a nav_msgs/msg/OccupancyGrid of (height, width) int8 `values` (for tests and tools; `width` and
    `height` override the info's, to make a malformed one)."""
    ts = typestore(distro)
    t = ts.types
    v = np.asarray(values, dtype=np.int8)
    stamp = t["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    x, y, yaw = (float(a) for a in origin)
    info = t["nav_msgs/msg/MapMetaData"](
        map_load_time=stamp, resolution=float(resolution), width=int(v.shape[1] if width is None else width),
        height=int(v.shape[0] if height is None else height),
        origin=t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x, y, 0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](0.0, 0.0, float(np.sin(yaw / 2)), float(np.cos(yaw / 2))),
        ),
    )
    msg = t["nav_msgs/msg/OccupancyGrid"](header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id), info=info,
                                          data=v.reshape(-1))
    return bytes(ts.serialize_cdr(msg, "nav_msgs/msg/OccupancyGrid"))
