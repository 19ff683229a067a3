"""Egress's command shaping and safety, free of any transport: feed it commands, e-stop messages and time, get what
the base is sent and when (docs/safety.md).

- `SafetyConfig`: the limits, the watchdog, the stale-command refusal and the e-stop heartbeat (egress's settings
  inherit them, so a deploy file's `egress` entry configures both egress and the evaluation);
- `Safety`: what to send at a given time: zero for a reason (watchdog, stale commands, e-stop), or the last accepted
  command within the velocity, acceleration/deceleration and jerk limits;
- `SafetyCycle`: when to send: on each accepted command, on an e-stop change, at the steady `rate_hz`, and at the
  moment a zero condition begins (the watchdog's deadline: last accepted command + `watchdog_timeout_s`, not the
  next steady tick). Egress's event loop and the closed-loop evaluation both drive one.

Times: `now` is a monotonic time [s]; command stamps are compared with `now_ns`, the wall clock [ns].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, Field, model_validator

Reason = Literal["planner", "ramp", "limit", "watchdog", "stale_command", "estop", "estop_heartbeat"]
ZERO_REASONS: frozenset[str] = frozenset({"watchdog", "stale_command", "estop", "estop_heartbeat"})


class SafetyConfig(BaseModel):
    """Egress's safety settings (the fields of egress's settings that shape commands)."""

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
    command_ramp_s: float | None = Field(
        None, gt=0, description="spread each accepted command's change over this time [s], in equal steps, one per "
        "output (the first at acceptance): 0.1 with rate_hz 20 and a 10 Hz planner sends half the change at once "
        "and the rest one period later, so what the base sees changes at the planner's rate instead of twice it "
        "in one period (None: step at once)"
    )
    jerk_limit: float | None = Field(None, gt=0, description="|d2v/dt2| limit [m/s^3] (None: off)")
    yaw_jerk_limit: float | None = Field(None, gt=0, description="|d2omega/dt2| limit [rad/s^3] (None: off)")
    estop_heartbeat_hz: float | None = Field(
        None, gt=0, description="heartbeat mode: the e-stop source must publish an EStop at least this often, or "
        "the output is zero (reason estop_heartbeat) until its next message; zero from start until the first one "
        "(None: off; an engaged e-stop latches either way) [Hz]"
    )

    @model_validator(mode="after")
    def _zero_allowed(self) -> SafetyConfig:
        lo, hi = self.v_limits
        if not lo <= 0.0 <= hi:
            raise ValueError(f"v_limits {list(self.v_limits)} must include 0 (the watchdog and e-stop send zero)")
        return self

    @classmethod
    def from_settings(cls, settings: BaseModel | dict) -> SafetyConfig:
        """The safety fields of egress's settings (an object or a service entry's `config` dict); other fields
        (output, ros2, zenoh, ...) are left out. Invalid values raise pydantic's ValidationError naming the field."""
        values = settings if isinstance(settings, dict) else settings.model_dump()
        return cls.model_validate({k: v for k, v in values.items() if k in cls.model_fields})


@dataclass
class SafetyOutput:
    v: float
    omega: float
    reason: Reason


class Safety:
    """The command shaping: feed it commands, e-stop messages and time, get what to send.

    Named event counters (`counts`) go into egress's heartbeat."""

    def __init__(self, settings: SafetyConfig) -> None:
        self.s = settings
        self.last_output = np.zeros(2)
        self.last_time: float | None = None  # when `last_output` was computed
        self.accel = np.zeros(2)  # the acceleration of the last output step (for the jerk limit)
        self.command: np.ndarray | None = None
        self.command_time = -np.inf  # arrival of the last accepted command
        self.ramp_from = np.zeros(2)  # the output when it arrived (`command_ramp_s`)
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
        self.ramp_from = self.last_output.copy()
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
        """The next time after `now` the zero condition changes with no new input (the loop sends then)."""
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
        ramping = False
        if s.command_ramp_s is not None:
            share = (now - self.command_time + 1.0 / s.rate_hz) / s.command_ramp_s
            if share < 1.0 - 1e-9:
                target = self.ramp_from + (target - self.ramp_from) * max(share, 0.0)
                ramping = True
        # the budget is the time since the last output, capped at two periods: a stalled loop banks no jump
        dt = 1.0 / s.rate_hz if self.last_time is None else min(max(0.0, now - self.last_time), 2.0 / s.rate_hz)
        out = np.array([self._slew(i, target[i], dt) for i in range(2)])
        reason: Reason = "planner" if np.allclose(out, self.command, rtol=0.0, atol=1e-9) else "limit"
        if reason == "limit" and ramping and np.allclose(out, target, rtol=0.0, atol=1e-9):
            reason = "ramp"
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
        # arrived (or within rounding of it: last + (err / dt) * dt need not be the target to the last bit, and the
        # base must get the planner's command exactly when no limit binds)
        if (err > 0.0 and out > target) or (err < 0.0 and out < target) or abs(target - out) <= 1e-12:
            out = target
        self.accel[axis] = (out - last) / dt
        return out


@dataclass
class Sent:
    """One output to send: what, and the stamp of the command it answers when it is the first output after that
    command was accepted (None: a repeat, a limit step or a zero; egress stamps those with its clock)."""

    output: SafetyOutput
    command_stamp_ns: int | None


_EPS_S = 1e-6  # a wake at the computed tick counts as the tick (float rounding of the sums)


class SafetyCycle:
    """When egress sends: on each accepted command, on an e-stop change, every 1 / `rate_hz`, and at the moment a
    zero condition begins (the watchdog's deadline). The caller feeds input, asks `step(now)` for what to send
    (None: nothing due) and sleeps `wait_s(now)` (input wakes it earlier)."""

    def __init__(self, config: SafetyConfig) -> None:
        self.config = config
        self.safety = Safety(config)
        self.period = 1.0 / config.rate_hz
        self.last_sent = -np.inf
        self._sent_zero: Reason | None = None  # the zero reason of the last output sent (None: it was not zero)
        self._new_stamp: int | None = None  # stamp of a command accepted since the last output
        self._estop_changed = False

    def on_command(self, v_ref: float, omega_ref: float, stamp_ns: int, now: float, now_ns: int) -> str | None:
        """Take a command (`Safety.on_command`); an accepted one is sent at the next `step`."""
        refusal = self.safety.on_command(v_ref, omega_ref, stamp_ns, now, now_ns)
        if refusal is None:
            self._new_stamp = stamp_ns
        return refusal

    def on_estop(self, engaged: bool, now: float) -> bool:
        changed = self.safety.on_estop(engaged, now)
        self._estop_changed = self._estop_changed or changed
        return changed

    def due(self, now: float) -> bool:
        """Whether an output is due at `now`."""
        return (
            self._new_stamp is not None
            or self._estop_changed
            or now - self.last_sent >= self.period - _EPS_S
            # a zero condition began (the watchdog's deadline passed) or ended since the last output
            or self.safety.zero_reason(now) != self._sent_zero
        )

    def step(self, now: float) -> Sent | None:
        """What to send at `now`, or None when nothing is due."""
        if not self.due(now):
            return None
        out = self.safety.output(now)
        sent = Sent(out, self._new_stamp if out.reason not in ZERO_REASONS else None)
        self.last_sent = now
        self._sent_zero = out.reason if out.reason in ZERO_REASONS else None
        self._new_stamp = None
        self._estop_changed = False
        return sent

    def next_due(self, now: float) -> float:
        """When the next output is due with no new input: the steady tick or the next zero-condition change."""
        if self.due(now):
            return now
        return float(min(self.last_sent + self.period, self.safety.next_change(now)))

    def wait_s(self, now: float) -> float:
        """How long the loop may sleep before the next output is due [s]."""
        return max(0.0, self.next_due(now) - now)
