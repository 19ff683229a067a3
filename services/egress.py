"""egress: turns planner `Command`s into what the base takes, and owns safety.

Outputs: `gpmppi/{robot}/base/cmd` (BaseCommand, for the simulator), or ROS 2 `geometry_msgs/msg/Twist` /
`TwistStamped` as CDR on the rmw_zenoh key (with its attachment) or a zenoh-bridge-ros2dds key.
Safety: commands older than `watchdog_timeout_s` give zero, sent at a steady `rate_hz`; velocity and
acceleration limits; an engaged e-stop on `gpmppi/{robot}/estop` gives zero until released.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from schemas import BaseCommand, Command, EStop
from services import ros2
from services.node import Node, NodeSettings


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


class Settings(NodeSettings):
    service: str = Field("egress", description="service name")
    output: Literal["sim", "ros2"] = Field("sim", description="where commands go")
    ros2: Ros2Output = Field(default_factory=Ros2Output, description="ROS 2 command output")
    rate_hz: float = Field(20.0, gt=0, description="steady output rate when no new command arrives [Hz]")
    watchdog_timeout_s: float = Field(0.5, gt=0, description="commands older than this are replaced by zero [s]")
    v_limits: tuple[float, float] = Field((-0.5, 2.0), description="forward velocity limits [m/s]")
    omega_limit: float = Field(3.1416, gt=0, description="|yaw rate| limit [rad/s]")
    # a safety envelope, not a shaping filter: the planner's own limits shape its commands
    accel_limit: float = Field(10.0, gt=0, description="|dv/dt| limit [m/s^2] (planner commands only)")
    yaw_accel_limit: float = Field(40.0, gt=0, description="|domega/dt| limit [rad/s^2] (planner commands only)")
    gid_seed: int | None = Field(None, description="seed of the rmw_zenoh source gid (None: random)")


@dataclass
class SafetyOutput:
    v: float
    omega: float
    reason: Literal["planner", "watchdog", "estop", "limit"]


class Safety:
    """The command shaping, free of Zenoh: feed it commands and time, get what to send."""

    def __init__(self, settings: Settings) -> None:
        self.s = settings
        self.last_output = np.zeros(2)
        # per axis: when the output last changed. The slew budget accrues from then (repeats of the same
        # value at the steady rate do not reset it), capped at two output periods so a long hold cannot
        # bank a jump
        self.change_time = np.full(2, -np.inf)
        self.command: np.ndarray | None = None
        self.command_time = -np.inf
        self.estop = False

    def on_command(self, v_ref: float, omega_ref: float, now: float) -> None:
        self.command = np.array([v_ref, omega_ref], dtype=np.float64)
        self.command_time = now

    def _set(self, value: np.ndarray, now: float) -> None:
        self.change_time[value != self.last_output] = now
        self.last_output = value

    def output(self, now: float) -> SafetyOutput:
        if self.estop:
            self._set(np.zeros(2), now)
            return SafetyOutput(0.0, 0.0, "estop")
        if self.command is None or now - self.command_time > self.s.watchdog_timeout_s:
            # a stale command must not keep the robot moving: zero at once (no ramp)
            self._set(np.zeros(2), now)
            return SafetyOutput(0.0, 0.0, "watchdog")
        target = self.command.copy()
        limited = np.array(
            [np.clip(target[0], *self.s.v_limits), np.clip(target[1], -self.s.omega_limit, self.s.omega_limit)]
        )
        dt = np.minimum(now - self.change_time, 2.0 / self.s.rate_hz)
        step = np.array([self.s.accel_limit, self.s.yaw_accel_limit]) * dt
        limited = np.clip(limited, self.last_output - step, self.last_output + step)
        reason: Literal["planner", "limit"] = "planner" if np.allclose(limited, target, atol=1e-9) else "limit"
        self._set(limited, now)
        return SafetyOutput(float(limited[0]), float(limited[1]), reason)


def run(settings: Settings) -> int:
    safety = Safety(settings)
    period = 1.0 / settings.rate_hz
    with Node(settings) as node:
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
        sequence = 1  # ROS 2 publishers count from 1
        last_sent = -np.inf
        last_reason = ""
        while node.ok():
            now = time.monotonic()
            estop: EStop | None = estop_sub.take()
            if estop is not None:
                if estop.engaged != safety.estop:
                    node.log.warning("e-stop %s: %s", "engaged" if estop.engaged else "released", estop.reason)
                safety.estop = estop.engaged
            cmd: Command | None = cmd_sub.take()
            if cmd is not None:
                safety.on_command(cmd.v_ref, cmd.omega_ref, now)
            if cmd is None and estop is None and now - last_sent < period:
                node.spin_once(min(settings.poll_s, period - (now - last_sent)))
                continue
            out = safety.output(now)
            if out.reason != last_reason and out.reason in ("watchdog", "estop"):
                node.log.warning("output zero: %s", out.reason)
            last_reason = out.reason
            stamp = cmd.header.stamp_ns if cmd is not None else time.time_ns()
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
            last_sent = now
            node.cycle()
            node.spin_once(0.0)
    return 0
