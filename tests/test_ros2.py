"""ROS 2 over Zenoh: what egress publishes decodes with rosbags to the commanded Twist on the exact rmw_zenoh
key (with its attachment); ingress turns rosbags-serialized Odometry into the right State."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore
from zenoh.ext import Int64, z_deserialize
from zenoh_helpers import (
    Collector,
    ServiceProcess,
    client,
    free_port,
    heartbeats,
    matched_publisher,
    router,
    settings,
    wait_for,
)

from schemas import Command, Header, State, decode, encode

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
# rmw_zenoh (jazzy) key of /jackal/cmd_vel, written out by hand: domain/namespace/topic/DDS type/RIHS01 hash
TWIST_KEY = (
    "0/jackal/cmd_vel/geometry_msgs::msg::dds_::Twist_/"
    "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
)


def _attachment(data: bytes) -> tuple[int, int, bytes]:
    keys_values = z_deserialize(tuple[str, Int64, str, Int64, str, bytes], zenoh.ZBytes(data))
    assert keys_values[0::2] == ("sequence_number", "source_timestamp", "source_gid")
    return int(keys_values[1]), int(keys_values[3]), bytes(keys_values[5])


def _drive(port: int, v: float, omega: float, n: int = 20) -> None:
    s = client(port)
    pub = matched_publisher(s, "gpmppi/r1/cmd")
    for _ in range(n):
        pub.put(encode(Command(v_ref=v, omega_ref=omega, header=Header(stamp_ns=time.time_ns()))))
        time.sleep(0.05)
    s.close()


def test_egress_twist_on_the_rmw_zenoh_key_decodes_with_rosbags(tmp_path: Path) -> None:
    assert TYPESTORE.hash_rihs01("geometry_msgs/msg/Twist") == TWIST_KEY.rsplit("/", 1)[1]
    port = free_port()
    with router(port):
        observer = client(port)
        col = Collector(observer, "0/**")
        health = Collector(observer, "gpmppi/**")
        cfg = settings("egress", port, output="ros2", ros2={"namespace": "/jackal", "topic": "cmd_vel"}, gid_seed=3)
        egress = ServiceProcess("egress", cfg, tmp_path)
        try:
            assert wait_for(lambda: bool(heartbeats(health, "r1", "egress")), 15.0), egress.log()
            t0 = time.time_ns()
            _drive(port, 0.8, -0.4)
            assert wait_for(lambda: len(col.on(TWIST_KEY)) > 5, 5.0), f"keys seen: {col.keys()}"
        finally:
            assert egress.stop() == 0
            observer.close()
    samples = col.on(TWIST_KEY)
    assert col.keys() == {TWIST_KEY}
    twists = [TYPESTORE.deserialize_cdr(p, "geometry_msgs/msg/Twist") for _, p, _ in samples]
    commanded = [(t.linear.x, t.angular.z) for t in twists if t.linear.x != 0.0]
    # after the acceleration-limited ramp, exactly the commanded velocities
    assert len(commanded) > 5 and commanded[-1] == pytest.approx((0.8, -0.4))
    assert all(0.0 < v <= 0.8 + 1e-12 and -0.4 - 1e-12 <= w < 0.0 for v, w in commanded)
    assert all((t.linear.y, t.linear.z, t.angular.x, t.angular.y) == (0, 0, 0, 0) for t in twists)
    attachments = [_attachment(a) for _, _, a in samples if a is not None]
    assert len(attachments) == len(samples)
    seqs = [a[0] for a in attachments]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    assert all(abs(a[1] - t0) < 30e9 for a in attachments)
    assert all(len(a[2]) == 16 and a[2] == attachments[0][2] for a in attachments)


def test_egress_twist_stamped_on_a_bridge_key(tmp_path: Path) -> None:
    port = free_port()
    with router(port):
        observer = client(port)
        col = Collector(observer, "jackal/**")
        health = Collector(observer, "gpmppi/**")
        ros2 = {"namespace": "jackal", "stamped": True, "key_style": "bridge", "frame_id": "base_link"}
        egress = ServiceProcess("egress", settings("egress", port, output="ros2", ros2=ros2), tmp_path)
        try:
            assert wait_for(lambda: bool(heartbeats(health, "r1", "egress")), 15.0), egress.log()
            _drive(port, 0.5, 0.25)
            assert wait_for(lambda: len(col.on("jackal/cmd_vel")) > 5, 5.0), f"keys seen: {col.keys()}"
        finally:
            assert egress.stop() == 0
            observer.close()
    msgs = [TYPESTORE.deserialize_cdr(p, "geometry_msgs/msg/TwistStamped") for _, p, _ in col.on("jackal/cmd_vel")]
    assert all(m.header.frame_id == "base_link" for m in msgs)
    assert any((m.twist.linear.x, m.twist.angular.z) == pytest.approx((0.5, 0.25)) for m in msgs)
    assert all(a is None for _, _, a in col.on("jackal/cmd_vel"))


def _odometry(x: float, y: float, yaw: float, v: float, omega: float, stamp_ns: int) -> bytes:
    t = TYPESTORE.types
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id="odom"
    )
    pose_cov = np.zeros(36)
    pose_cov[0], pose_cov[7], pose_cov[35], pose_cov[1], pose_cov[6] = 0.01, 0.02, 0.03, 0.004, 0.004
    twist_cov = np.zeros(36)
    twist_cov[0], twist_cov[35] = 0.05, 0.06
    pose = t["geometry_msgs/msg/PoseWithCovariance"](
        pose=t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
        ),
        covariance=pose_cov,
    )
    vec = t["geometry_msgs/msg/Vector3"]
    twist = t["geometry_msgs/msg/TwistWithCovariance"](
        twist=t["geometry_msgs/msg/Twist"](linear=vec(x=v, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=omega)),
        covariance=twist_cov,
    )
    msg = t["nav_msgs/msg/Odometry"](header=header, child_frame_id="base_link", pose=pose, twist=twist)
    return bytes(TYPESTORE.serialize_cdr(msg, "nav_msgs/msg/Odometry"))


def test_ingress_turns_ros2_odometry_into_state(tmp_path: Path) -> None:
    key = "0/odom/nav_msgs::msg::dds_::Odometry_/" + TYPESTORE.hash_rihs01("nav_msgs/msg/Odometry")
    port = free_port()
    with router(port):
        observer = client(port)
        col = Collector(observer)
        ingress = ServiceProcess("ingress", settings("ingress", port, source="ros2", max_age_s=1.0), tmp_path)
        try:
            assert wait_for(lambda: bool(heartbeats(col, "r1", "ingress")), 15.0), ingress.log()
            pub = matched_publisher(observer, key)
            pub.put(b"\x00\x01\x00\x00garbage")  # malformed CDR
            time.sleep(0.2)
            pub.put(_odometry(1.0, 2.0, 0.3, 0.7, 0.1, time.time_ns() - 5 * 10**9))  # stale
            time.sleep(0.2)
            stamp = time.time_ns()
            pub.put(_odometry(3.0, -4.0, 2.5, 1.25, -0.5, stamp))
            assert wait_for(lambda: bool(col.on("gpmppi/r1/state")), 5.0), ingress.log()
            assert wait_for(lambda: any(h.rejected >= 2 for h in heartbeats(col, "r1", "ingress")), 15.0)
        finally:
            assert ingress.stop() == 0
            observer.close()
    states = [decode(State, p) for _, p, _ in col.on("gpmppi/r1/state")]
    assert len(states) == 1
    s = states[0]
    assert (s.x, s.y, s.theta, s.v, s.omega) == pytest.approx((3.0, -4.0, 2.5, 1.25, -0.5))
    assert s.header.stamp_ns == stamp and s.header.frame_id == "odom"
    cov = np.asarray(s.covariance).reshape(5, 5)
    assert np.diag(cov) == pytest.approx([0.01, 0.02, 0.03, 0.05, 0.06])
    assert cov[0, 1] == pytest.approx(0.004) and cov[1, 0] == pytest.approx(0.004)
    log = ingress.log()
    assert "stale" in log and "not a nav_msgs/msg/Odometry" in log


def test_ingress_counts_bad_odometry_that_a_newer_message_replaced_before_its_loop_took_it() -> None:
    from services.ingress import Settings as IngressSettings
    from services.ingress import ros2_odometry_inbox
    from services.runtime.node import Node

    key = "0/odom/nav_msgs::msg::dds_::Odometry_/" + TYPESTORE.hash_rihs01("nav_msgs/msg/Odometry")
    port = free_port()
    with router(port):
        node = Node(IngressSettings(**settings("ingress", port, source="ros2")), install_signals=False)
        observer = client(port)
        try:
            with node:
                inbox = ros2_odometry_inbox(node, node.settings)
                pub = matched_publisher(observer, key)
                good = _odometry(3.0, -4.0, 2.5, 1.25, -0.5, time.time_ns())
                assert wait_for(lambda: (pub.put(good), inbox.take())[1] is not None, 5.0)
                time.sleep(0.2)
                inbox.take()  # a late warm-up message
                bad = [b"\x00\x01\x00\x00garbage", b"", b"\x00\x01\x00\x00" + bytes(7)]
                # a burst while the loop takes nothing: each bad one is replaced by the next before it is taken
                for payload in bad:
                    pub.put(payload)
                pub.put(good)
                assert wait_for(lambda: node.counters.rejected == len(bad), 10.0), node.counters.rejected
                newest = inbox.take()
                assert newest is not None and newest.payload.to_bytes() == good and inbox.take() is None
                assert "not a nav_msgs/msg/Odometry" in node.counters.last_error
        finally:
            observer.close()
