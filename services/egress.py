"""egress: turns planner `Command`s into what the base takes, and owns safety.

Outputs: `gpmppi/{robot}/base/cmd` (BaseCommand, for the simulator), or ROS 2 `geometry_msgs/msg/Twist` /
`TwistStamped` as CDR on the rmw_zenoh key (with its attachment) or a zenoh-bridge-ros2dds key.
Safety (`gpmppi.safety`: `Safety` and its `SafetyCycle`, free of Zenoh, which the evaluation drives too;
docs/safety.md): no command for `watchdog_timeout_s` gives zero at once, then
zero at a steady `rate_hz`; commands whose own stamp is older than `max_command_age_s` are refused; velocity limits,
separate acceleration and deceleration limits per axis, an optional jerk limit; an e-stop on `gpmppi/{robot}/estop`
latches zero until an explicit release, and in heartbeat mode the e-stop source must keep publishing or the output
is zero. Every output carries its reason.
"""

from __future__ import annotations

import time
from typing import Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, model_validator

from gpmppi.safety import ZERO_REASONS, Reason, Safety, SafetyConfig, SafetyCycle
from schemas import BaseCommand, Command, EStop
from services.codec import ros2
from services.runtime.node import Node
from services.runtime.node_settings import NodeSettings


class Ros2Output(BaseModel):
    model_config = ConfigDict(extra="forbid")

    topic: str = Field("cmd_vel", description="ROS 2 velocity topic (relative to namespace)")
    namespace: str = Field("", description="ROS 2 namespace, e.g. /jackal")
    domain_id: int = Field(0, ge=0, description="ROS_DOMAIN_ID (rmw_zenoh key prefix)")
    stamped: bool = Field(False, description="TwistStamped instead of Twist")
    frame_id: str = Field("base_link", description="header.frame_id of TwistStamped")
    key_style: ros2.KeyStyle = Field("rmw_zenoh", description="rmw_zenoh key + attachment, or bridge key")
    distro: ros2.Distro = Field("jazzy", description="ROS 2 distro (type hash in the rmw_zenoh key)")
    key: str | None = Field(None, description="explicit Zenoh key (overrides the fields above)")

    @property
    def ros_type(self) -> str:
        return "geometry_msgs/msg/TwistStamped" if self.stamped else "geometry_msgs/msg/Twist"

    def key_expr(self) -> str:
        if self.key:
            return self.key
        return ros2.topic_key(self.topic, self.ros_type, self.namespace, self.domain_id, self.key_style, self.distro)


# the ROS 2 base stops on its own when cmd_vel pauses (Jackal: 0.25 s ROS 1, 0.5 s ROS 2): repeats at >= 10 Hz
# keep that timeout for real faults only
ROS2_MIN_RATE_HZ = 10.0

# one vocabulary with the wire: a reason the message cannot carry would fail at the first put
assert set(get_args(Reason)) == set(get_args(BaseCommand.model_fields["reason"].annotation))


class Settings(NodeSettings, SafetyConfig):
    """Egress's settings: how it joins and where it sends (here), and the safety fields (`gpmppi.safety.SafetyConfig`,
    shared with the evaluation)."""

    service: str = Field("egress", description="service name")
    output: Literal["sim", "ros2"] = Field("sim", description="where commands go")
    ros2: Ros2Output = Field(default_factory=Ros2Output, description="ROS 2 command output")
    gid_seed: int | None = Field(None, description="seed of the rmw_zenoh source gid (None: random)")

    @model_validator(mode="after")
    def _safe(self) -> Settings:
        if self.output == "ros2" and self.rate_hz < ROS2_MIN_RATE_HZ:
            raise ValueError(
                f"rate_hz {self.rate_hz} is below {ROS2_MIN_RATE_HZ} Hz with output ros2: the base's own cmd_vel "
                f"timeout would stop it between repeats; set rate_hz to {ROS2_MIN_RATE_HZ} or more"
            )
        return self


def run(settings: Settings) -> int:
    with Node(settings) as node:
        return serve(node, settings)


def serve(node: Node, settings: Settings, cycle: SafetyCycle | None = None) -> int:
    """Egress's event loop on an open node, until it is stopped: decode, `SafetyCycle`, encode. `cycle`: one made
    from `settings` by the caller, who can then read its state (tests); None: made here."""
    cycle = cycle or SafetyCycle(SafetyConfig.from_settings(settings))
    cmd_sub = node.subscribe("cmd")
    estop_sub = node.subscribe("estop")
    if settings.output == "sim":
        base = node.publisher("base_cmd")
        ros_pub = None
    else:
        import zenoh

        base = None
        assert node.session is not None
        key = settings.ros2.key_expr()
        ros_pub = node.session.declare_publisher(key, encoding=zenoh.Encoding("application/cdr"))
        gid = ros2.new_gid(settings.gid_seed)
        node.log.info("ROS 2 %s on %s", settings.ros2.ros_type, key)
    if settings.estop_heartbeat_hz is not None:
        node.log.info("e-stop heartbeat mode: zero until an EStop arrives at least every %.3f s",
                      1.0 / settings.estop_heartbeat_hz)
    sequence = 1  # ROS 2 publishers count from 1
    last_reason = ""
    while node.ok():
        now = time.monotonic()
        estop: EStop | None = estop_sub.take()
        if estop is not None and cycle.on_estop(estop.engaged, now):
            node.log.warning("e-stop %s: %s", "engaged" if estop.engaged else "released", estop.reason)
        cmd: Command | None = cmd_sub.take()
        if cmd is not None:
            refusal = cycle.on_command(cmd.v_ref, cmd.omega_ref, cmd.header.stamp_ns, now, time.time_ns())
            if refusal is not None:
                node.reject(refusal)
        # send on a new command, an e-stop change, the steady period, and the moment a timeout fires (a timer at
        # its deadline: the wait below ends then, and `step` sends the zero at once)
        sent = cycle.step(now)
        if sent is None:
            node.spin_once(min(settings.poll_s, cycle.wait_s(time.monotonic())))
            continue
        out = sent.output
        if out.reason != last_reason:
            if out.reason in ZERO_REASONS:
                node.log.warning("output zero: %s", out.reason)
            elif last_reason in ZERO_REASONS:
                node.log.info("output follows the planner again (was %s)", last_reason)
        last_reason = out.reason
        # a new command keeps its stamp (the state it was planned from: the terrain estimator pairs by it)
        stamp = sent.command_stamp_ns if sent.command_stamp_ns is not None else time.time_ns()
        if base is not None:
            msg = BaseCommand(v=out.v, omega=out.omega, reason=out.reason)
            msg.header.stamp_ns = stamp
            msg.header.frame_id = "base_link"
            base.put(msg)
        elif ros_pub is not None:
            now_ns = time.time_ns()
            payload = ros2.twist_cdr(
                out.v, out.omega, settings.ros2.stamped, settings.ros2.frame_id, now_ns, settings.ros2.distro
            )
            attachment = None
            if settings.ros2.key_style == "rmw_zenoh":
                attachment = ros2.Attachment(sequence, now_ns, gid).to_bytes()
            ros_pub.put(payload, attachment=attachment)
            sequence += 1
            node.counters.published += 1
        _health(node, cycle.safety, out.reason)
        node.cycle()
        node.spin_once(0.0)
    return 0


def _health(node: Node, safety: Safety, reason: Reason) -> None:
    """Safety's counters and the output's condition into the heartbeat."""
    c = node.counters
    with c.lock:
        c.counts.update(safety.counts)
        c.flags.update({
            "watchdog": reason in ("watchdog", "stale_command"),
            "stale_command": reason == "stale_command",
            "estop": safety.estop,
            "estop_heartbeat_lost": reason == "estop_heartbeat",
            "limited": reason == "limit",
        })
        # zero for want of input is degraded; an engaged e-stop is an order, not a fault
        c.status = "degraded" if reason in ("watchdog", "stale_command", "estop_heartbeat") else "ok"
