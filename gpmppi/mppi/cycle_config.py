"""The planning cycle's settings (`gpmppi.mppi.cycle.PlannerCycle`): its state checks, weight ageing, jump detection,
delay compensation, grid ageing and, through `CautionConfig`, its caution on unknown ground."""

from __future__ import annotations

from pydantic import Field, model_validator

from gpmppi.mppi.caution import CautionConfig

__all__ = ["CycleConfig"]


class CycleConfig(CautionConfig):
    """The planning cycle's checks and delay compensation, and its caution on unknown ground (`CautionConfig`)."""

    max_state_age_s: float = Field(0.5, gt=0, description="do not plan from a state older than this [s]")
    max_state_future_s: float = Field(
        0.2, ge=0, description="do not plan from a state stamped further than this in the future: the clock skew "
        "tolerated between the state's source and this host [s]"
    )
    weights_stale_after_s: float = Field(
        1.0, gt=0, description="terrain weights not refreshed for this long are flagged stale (kept, Plan."
        "weights_stale, heartbeat flag weights_stale, status degraded) [s]"
    )
    weights_fallback_after_s: float = Field(
        5.0, gt=0, description="terrain weights not refreshed for this long are replaced by the prior (uniform) [s]"
    )
    jump_distance_m: float = Field(
        0.5, gt=0, description="an odometry jump: consecutive states further apart than this plus what their speed "
        "explains over their stamp gap; resets the warm start [m]"
    )
    jump_yaw_rad: float = Field(
        0.5, gt=0, description="an odometry jump in yaw: consecutive headings further apart than this plus what "
        "their yaw rate explains [rad]"
    )
    compensate_delay: bool = Field(
        True, description="plan from the state predicted to when the command takes effect (state age + compute + "
        "actuation_delay_s), not from the measured one; the age is this host's clock minus the state's stamp, so "
        "the two clocks must agree (one host, or synchronised clocks): turn it off otherwise"
    )
    actuation_delay_s: float = Field(
        0.005, ge=0, description="from the command leaving the cycle to the base applying it (egress hop, base "
        "tick; in a simulation: the whole command latency) [s]"
    )
    max_costmap_age_s: float | None = Field(
        None, gt=0, description="a grid that came from a sensor (`set_costmap`, e.g. Nav2's local costmap) and was not "
        "refreshed for this long is too old to plan among: goal tasks among it are not planned (no command, so "
        "egress's watchdog stops the robot rather than let it drive blind) until a new grid arrives [s]; None: grids "
        "never age (a static map)"
    )

    @model_validator(mode="after")
    def _fallback_after_stale(self) -> CycleConfig:
        if self.weights_fallback_after_s < self.weights_stale_after_s:
            raise ValueError(
                f"weights_fallback_after_s {self.weights_fallback_after_s} is shorter than weights_stale_after_s "
                f"{self.weights_stale_after_s}: weights are flagged stale before they are replaced by the prior"
            )
        return self
