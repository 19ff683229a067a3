"""egress: turns planner `Command`s into what the base takes, and owns safety.

Outputs: `gpmppi/{robot}/base/cmd` (BaseCommand, for the simulator), or ROS 2 `geometry_msgs/msg/Twist` /
`TwistStamped` as CDR on the rmw_zenoh key (with its attachment) or a zenoh-bridge-ros2dds key.
Safety (`Safety`, free of Zenoh; docs/safety.md): no command for `watchdog_timeout_s` gives zero at once, then
zero at a steady `rate_hz`; commands whose own stamp is older than `max_command_age_s` are refused; velocity limits,
separate acceleration and deceleration limits per axis, an optional jerk limit; an e-stop on `gpmppi/{robot}/estop`
latches zero until an explicit release, and in heartbeat mode the e-stop source must keep publishing or the output
is zero. Every output carries its reason.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

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


# the ROS 2 base stops on its own when cmd_vel pauses (Jackal: 0.25 s ROS 1, 0.5 s ROS 2): repeats at >= 10 Hz
# keep that timeout for real faults only
ROS2_MIN_RATE_HZ = 10.0

Reason = Literal["planner", "limit", "watchdog", "stale_command", "estop", "estop_heartbeat"]
ZERO_REASONS: frozenset[str] = frozenset({"watchdog", "stale_command", "estop", "estop_heartbeat"})
# one vocabulary with the wire: a reason the message cannot carry would fail at the first put
assert set(get_args(Reason)) == set(get_args(BaseCommand.model_fields["reason"].annotation))


class Settings(NodeSettings):
    service: str = Field("egress", description="service name")
    output: Literal["sim", "ros2"] = Field("sim", description="where commands go")
    ros2: Ros2Output = Field(default_factory=Ros2Output, description="ROS 2 command output")
    rate_hz: float = Field(
        20.0, gt=0, description="steady output rate when no new command arrives [Hz] (ROS 2 output: >= 10)"
    )
    watchdog_timeout_s: float = Field(
        0.25, gt=0, description="no accepted command for this long: zero at once, then zero at rate_hz [s] "
        "(the Jackal base's ROS 1 cmd_vel_timeout)"
    )
    max_command_age_s: float | None = Field(
        0.5, gt=0, description="refuse a command whose header stamp (the stamp of the state it was planned from) "
        "is older than this by this host's wall clock [s]; the planner's and this host's clocks must agree "
        "(None: off)"
    )
    max_command_future_s: float = Field(
        0.2, ge=0, description="refuse a command stamped further than this in the future (clock skew) [s]"
    )
    v_limits: tuple[float, float] = Field((-0.5, 2.0), description="forward velocity limits [m/s] (must include 0)")
    omega_limit: float = Field(3.1416, gt=0, description="|yaw rate| limit [rad/s]")
    # the defaults are a safety envelope, not a shaping filter (slowing down twice as fast as speeding up): the
    # Jackal base's own 2.0 / 4.0 m/s^2 on v cost tracking in simulation (docs/safety.md), so deploy/robot.yaml sets
    # them where the base applies them anyway
    accel_limit: float = Field(
        10.0, gt=0, description="|v| increasing: |dv/dt| limit [m/s^2] (planner commands; zeros are not ramped)"
    )
    decel_limit: float = Field(20.0, gt=0, description="|v| decreasing or changing sign: |dv/dt| limit [m/s^2]")
    yaw_accel_limit: float = Field(40.0, gt=0, description="|omega| increasing: |domega/dt| limit [rad/s^2]")
    yaw_decel_limit: float = Field(
        80.0, gt=0, description="|omega| decreasing or changing sign: |domega/dt| limit [rad/s^2]"
    )
    jerk_limit: float | None = Field(None, gt=0, description="|d2v/dt2| limit [m/s^3] (None: off)")
    yaw_jerk_limit: float | None = Field(None, gt=0, description="|d2omega/dt2| limit [rad/s^3] (None: off)")
    estop_heartbeat_hz: float | None = Field(
        None, gt=0, description="heartbeat mode: the e-stop source must publish an EStop at least this often, or "
        "the output is zero (reason estop_heartbeat) until its next message; zero from start until the first one "
        "(None: off; an engaged e-stop latches either way) [Hz]"
    )
    gid_seed: int | None = Field(None, description="seed of the rmw_zenoh source gid (None: random)")

    @model_validator(mode="after")
    def _safe(self) -> Settings:
        if self.output == "ros2" and self.rate_hz < ROS2_MIN_RATE_HZ:
            raise ValueError(
                f"rate_hz {self.rate_hz} is below {ROS2_MIN_RATE_HZ} Hz with output ros2: the base's own cmd_vel "
                f"timeout would stop it between repeats; set rate_hz to {ROS2_MIN_RATE_HZ} or more"
            )
        lo, hi = self.v_limits
        if not lo <= 0.0 <= hi:
            raise ValueError(f"v_limits {list(self.v_limits)} must include 0 (the watchdog and e-stop send zero)")
        return self


@dataclass
class SafetyOutput:
    v: float
    omega: float
    reason: Reason


class Safety:
    """The command shaping, free of Zenoh: feed it commands, e-stop messages and time, get what to send.

    `now` is a monotonic time [s]; command stamps are compared with `now_ns`, the wall clock [ns]. Named event
    counters (`counts`) go into egress's heartbeat."""

    def __init__(self, settings: Settings) -> None:
        self.s = settings
        self.last_output = np.zeros(2)
        self.last_time: float | None = None  # when `last_output` was computed
        self.accel = np.zeros(2)  # the acceleration of the last output step (for the jerk limit)
        self.command: np.ndarray | None = None
        self.command_time = -np.inf  # arrival of the last accepted command
        self.refused_time = -np.inf  # arrival of the last refused one
        self.estop = False  # latched: set by an engaged EStop, cleared only by a released one
        self.estop_seen = -np.inf  # arrival of the last EStop (heartbeat mode)
        self.last_reason: Reason | None = None
        self.counts: dict[str, int] = {}
        self._limits = (
            (settings.accel_limit, settings.decel_limit, settings.jerk_limit),
            (settings.yaw_accel_limit, settings.yaw_decel_limit, settings.yaw_jerk_limit),
        )

    def _count(self, name: str) -> None:
        self.counts[name] = self.counts.get(name, 0) + 1

    # ---- input
    def on_command(self, v_ref: float, omega_ref: float, stamp_ns: int, now: float, now_ns: int) -> str | None:
        """Take a command; returns why it was refused (it then changes nothing), or None."""
        s = self.s
        age_s = (now_ns - stamp_ns) / 1e9
        refusal = None
        if not (np.isfinite(v_ref) and np.isfinite(omega_ref)):
            refusal, counter = f"command ({v_ref}, {omega_ref}) is not finite", "command_nonfinite"
        elif s.max_command_age_s is not None and age_s > s.max_command_age_s:
            refusal, counter = (
                f"command stamp is {age_s:.3f} s old (max_command_age_s {s.max_command_age_s}): refused; commands "
                "carry the stamp of the state they were planned from, so the planner or its input is lagging, or "
                "the clocks disagree", "command_stale",
            )
        elif -age_s > s.max_command_future_s:
            refusal, counter = (
                f"command stamped {-age_s:.3f} s in the future (max_command_future_s {s.max_command_future_s}): "
                "refused; the planner's clock is ahead of this host's", "command_future",
            )
        if refusal is not None:
            self._count(counter)
            self.refused_time = now
            return refusal
        self.command = np.array([v_ref, omega_ref], dtype=np.float64)
        self.command_time = now
        return None

    def on_estop(self, engaged: bool, now: float) -> bool:
        """Take an e-stop message; True when the latch changed."""
        self.estop_seen = now
        if engaged == self.estop:
            return False
        self.estop = engaged
        self._count("estop_engaged" if engaged else "estop_released")
        return True

    # ---- output
    def zero_reason(self, now: float) -> Reason | None:
        """Why the output must be zero now, or None."""
        s = self.s
        if self.estop:
            return "estop"
        if s.estop_heartbeat_hz is not None and now - self.estop_seen >= 1.0 / s.estop_heartbeat_hz:
            return "estop_heartbeat"
        if self.command is None or now - self.command_time >= s.watchdog_timeout_s:
            # commands still arrive but are refused: say so (a lagging planner or skewed clocks, not a dead one)
            return "stale_command" if now - self.refused_time < s.watchdog_timeout_s else "watchdog"
        return None

    def next_change(self, now: float) -> float:
        """The next time the zero condition changes with no new input (the loop sends then, not a period later)."""
        s = self.s
        times = [np.inf]
        if not self.estop and self.command is not None:
            times.append(self.command_time + s.watchdog_timeout_s)
            times.append(self.refused_time + s.watchdog_timeout_s)
        if s.estop_heartbeat_hz is not None:
            times.append(self.estop_seen + 1.0 / s.estop_heartbeat_hz)
        future = [t for t in times if t > now]
        return min(future) if future else np.inf

    def output(self, now: float) -> SafetyOutput:
        zero = self.zero_reason(now)
        if zero is not None:
            # a stale command must not keep the robot moving: zero at once (no ramp)
            if zero != self.last_reason:
                self._count(zero)  # how often each zero condition began
            self.last_output = np.zeros(2)
            self.accel = np.zeros(2)
            self.last_time = now
            self.last_reason = zero
            return SafetyOutput(0.0, 0.0, zero)
        assert self.command is not None
        s = self.s
        v, omega = self.command
        target = np.array([np.clip(v, *s.v_limits), np.clip(omega, -s.omega_limit, s.omega_limit)])
        # the budget is the time since the last output, capped at two periods: a stalled loop banks no jump
        dt = 1.0 / s.rate_hz if self.last_time is None else min(max(0.0, now - self.last_time), 2.0 / s.rate_hz)
        out = np.array([self._slew(i, target[i], dt) for i in range(2)])
        reason: Reason = "planner" if np.allclose(out, self.command, rtol=0.0, atol=1e-9) else "limit"
        if reason == "limit":
            self._count("limited")
        self.last_output = out
        self.last_time = now
        self.last_reason = reason
        return SafetyOutput(float(out[0]), float(out[1]), reason)

    def _slew(self, axis: int, target: float, dt: float) -> float:
        """One axis, from the last output toward `target` within the acceleration/deceleration (and jerk) limits."""
        last, a_prev = float(self.last_output[axis]), float(self.accel[axis])
        if dt <= 0.0:
            return last
        accel_limit, decel_limit, jerk = self._limits[axis]
        err = target - last
        # accelerating: moving away from zero in the same direction (ROS 2 diff_drive_controller's rule)
        accelerating = abs(target) >= abs(last) and target * last >= 0.0
        a_max = accel_limit if accelerating else decel_limit
        a = float(np.clip(err / dt, -a_max, a_max))
        if jerk is not None:
            a = float(np.clip(a, a_prev - jerk * dt, a_prev + jerk * dt))
            # no faster than the jerk limit can bring the acceleration back to zero on arrival (no overshoot)
            a_arrive = float(np.sqrt(2.0 * jerk * abs(err)))
            a = float(np.clip(a, -a_arrive, a_arrive))
        out = last + a * dt
        if (err > 0.0 and out > target) or (err < 0.0 and out < target) or err == 0.0:
            out = target
        self.accel[axis] = (out - last) / dt
        return out


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
        if settings.estop_heartbeat_hz is not None:
            node.log.info("e-stop heartbeat mode: zero until an EStop arrives at least every %.3f s",
                          1.0 / settings.estop_heartbeat_hz)
        sequence = 1  # ROS 2 publishers count from 1
        last_sent = -np.inf
        last_reason = ""
        while node.ok():
            now = time.monotonic()
            estop: EStop | None = estop_sub.take()
            estop_changed = False
            if estop is not None:
                estop_changed = safety.on_estop(estop.engaged, now)
                if estop_changed:
                    node.log.warning("e-stop %s: %s", "engaged" if estop.engaged else "released", estop.reason)
            cmd: Command | None = cmd_sub.take()
            if cmd is not None:
                refusal = safety.on_command(cmd.v_ref, cmd.omega_ref, cmd.header.stamp_ns, now, time.time_ns())
                if refusal is not None:
                    node.reject(refusal)
                    cmd = None
            # send on a new command, an e-stop change, the steady period, and the moment a timeout fires
            next_change = safety.next_change(now)
            if cmd is None and not estop_changed and now - last_sent < period and now < next_change:
                node.spin_once(min(settings.poll_s, period - (now - last_sent), next_change - now))
                continue
            out = safety.output(now)
            if out.reason != last_reason:
                if out.reason in ZERO_REASONS:
                    node.log.warning("output zero: %s", out.reason)
                elif last_reason in ZERO_REASONS:
                    node.log.info("output follows the planner again (was %s)", last_reason)
            last_reason = out.reason
            _health(node, safety, out.reason)
            # a new command keeps its stamp (the state it was planned from: the terrain estimator pairs by it)
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
