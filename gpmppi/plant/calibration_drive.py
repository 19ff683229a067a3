"""The calibration drive's cycle, free of any transport: states in, commands out (the `calibrate` service drives it).

A robot's GP, nominal model and terrain calibration are fitted from logs of it driving on each ground; this cycle
makes those logs. On the first state it centres the area on the robot's pose; on each state it returns the command
to hold until the next one: the current `AreaExcitation` segment's command at the state's time (segments are
indexed by time since their start, so an odometry rate other than 1 / dt keeps their durations), a new segment from
the robot's pose when one ends, a turn back toward the centre when the robot drifts into the margin heading out.
It counts the distance (position steps of the states) and the time (state stamps); once the target is reached it
returns zero, and `done` turns true after the robot stood still for `stop_s`.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, Field, model_validator

from gpmppi.plant.area_excitation import MIN_AREA_M, Area, AreaExcitation

NS = 1_000_000_000


class DriveConfig(BaseModel):
    """What a calibration drive drives: area, speed cap and target (a distance, a time, or both: whichever first)."""

    area_m: float = Field(20.0, ge=MIN_AREA_M, le=10_000.0, description="side of the square area, centred on the "
                          "robot's first pose, that the drive stays inside [m]")
    margin_m: float | None = Field(None, gt=0, description="distance kept from the area's edges (None: 2 m, or a "
                                   "quarter of the side in small areas) [m]")
    v_max: float = Field(1.5, gt=0, le=2.0, description="speed cap of the commands [m/s]")
    w_max: float = Field(float(np.pi), gt=0, le=float(np.pi), description="yaw-rate cap of the commands [rad/s]")
    distance_m: float | None = Field(None, gt=0, description="stop after driving this far [m] (None: no limit)")
    duration_s: float | None = Field(None, gt=0, description="stop after driving this long [s] (None: no limit)")
    seed: int = Field(0, ge=0, description="seed of the command stream")
    lane_holds: float = Field(0.0, ge=0.0, lt=1.0, description="share of the segments that are long holds at the "
                              "planner's lane commands (`Excitation.lane_hold`), for a calibration-only log (0: none, "
                              "the plain drive) [1]")
    dt: float = Field(0.1, gt=0, le=1.0, description="tick of the command stream (the GP model's step) [s]")
    stop_s: float = Field(1.0, ge=0, description="zero commanded this long after the target before the drive is "
                          "done (the robot brakes to rest on the record) [s]")

    @model_validator(mode="after")
    def _has_target(self) -> DriveConfig:
        if self.distance_m is None and self.duration_s is None:
            raise ValueError("a calibration drive needs a target: distance_m or duration_s")
        if self.margin_m is not None and 2 * self.margin_m >= self.area_m:
            raise ValueError(f"margin_m {self.margin_m} leaves nothing of a {self.area_m} m area; make it smaller")
        return self


class CalibrationDrive:
    """One calibration drive: `on_state(x, stamp_ns)` -> the [v_ref, omega_ref] to command until the next state."""

    def __init__(self, config: DriveConfig) -> None:
        self.config = config
        self.excitation: AreaExcitation | None = None
        self.distance = 0.0  # [m] driven so far (position steps of the states)
        self.elapsed = 0.0  # [s] since the first state
        self.target_at: float | None = None  # elapsed time [s] at which the target was reached
        self._first: int | None = None
        self._last_xy: np.ndarray | None = None
        self._segment = np.zeros((0, 2))
        self._segment_start = 0
        self._returning = False

    @property
    def area(self) -> Area | None:
        return None if self.excitation is None else self.excitation.area

    @property
    def lane_holds(self) -> int:
        """Lane holds handed out so far (`DriveConfig.lane_holds`)."""
        return 0 if self.excitation is None else self.excitation.lane_held

    @property
    def reached(self) -> bool:
        return self.target_at is not None

    @property
    def done(self) -> bool:
        return self.target_at is not None and self.elapsed - self.target_at >= self.config.stop_s

    def _target_reached(self) -> bool:
        c = self.config
        return ((c.distance_m is not None and self.distance >= c.distance_m)
                or (c.duration_s is not None and self.elapsed >= c.duration_s))

    def on_state(self, x: np.ndarray, stamp_ns: int) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        c = self.config
        if self.excitation is None:
            area = Area.square(x[:2], c.area_m)
            self.excitation = AreaExcitation(area, c.seed, c.dt, c.v_max, c.w_max, c.margin_m,
                                             lane_holds=c.lane_holds)
            self._first = stamp_ns
        assert self._first is not None
        if self._last_xy is not None:
            self.distance += float(np.hypot(*(x[:2] - self._last_xy)))
        self._last_xy = x[:2].copy()
        self.elapsed = (stamp_ns - self._first) / NS
        if self.target_at is None and self._target_reached():
            self.target_at = self.elapsed
        if self.target_at is not None:
            return np.zeros(2)
        exc = self.excitation
        k = int((stamp_ns - self._segment_start) / NS / c.dt + 1e-6)
        if not self._returning and exc.heading_out(x):
            # the robot left its prediction (slip, a slow start): turn back now, not at the segment's end
            self._segment, self._returning, k = exc.turn_back(x), True, 0
            self._segment_start = stamp_ns
        elif k >= len(self._segment):
            start = exc.returns
            self._segment = exc.next_segment(x)
            self._returning = exc.returns > start
            self._segment_start, k = stamp_ns, 0
        return self._segment[k].copy()
