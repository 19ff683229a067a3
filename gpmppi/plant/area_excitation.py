"""An excitation kept inside a free area: the calibration drive's commands for a real robot (`gpmppi calibrate
drive`), `Excitation`'s segments with each one's path predicted first, turning back toward the centre where a segment
would leave the area."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpmppi.plant.excitation import LANE_HOLD_S, Excitation

MIN_AREA_M = 6.0  # the smallest square side an area excitation keeps a robot inside [m]
MOTOR_LAG_S = 0.3  # the velocity lag of the path prediction (the Jackal-sized physics plant settles in ~1 s) [s]
STOP_TAIL_S = 1.5  # every accepted segment leaves room to brake to rest after it, whatever follows [s]


@dataclass(frozen=True)
class Area:
    """An axis-aligned rectangle in the odometry frame: centre [m] and half side lengths [m]."""

    cx: float
    cy: float
    half_x: float
    half_y: float

    @classmethod
    def square(cls, centre: np.ndarray | tuple[float, float], side: float) -> Area:
        return cls(float(centre[0]), float(centre[1]), 0.5 * side, 0.5 * side)

    def inside(self, xy: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Per point of `xy` ((2,) or (n, 2)): whether it lies `margin` or more inside the edges, (n,) bool."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return ((np.abs(xy[:, 0] - self.cx) <= self.half_x - margin)
                & (np.abs(xy[:, 1] - self.cy) <= self.half_y - margin))

    def contains(self, xy: np.ndarray, margin: float = 0.0) -> bool:
        """Whether every point of `xy` ((2,) or (n, 2)) lies `margin` or more inside the edges."""
        return bool(np.all(self.inside(xy, margin)))


def predict_path(pose: np.ndarray, commands: np.ndarray, dt: float, tail_s: float = STOP_TAIL_S) -> np.ndarray:
    """Positions (n + tail, 2) of a kinematic unicycle from `pose` [X, Y, yaw, v, omega] under `commands`, the
    velocities following each command with a first-order lag (MOTOR_LAG_S), then braking to rest for `tail_s`."""
    tail = np.zeros((int(round(tail_s / dt)), 2))
    cmds = np.vstack([np.asarray(commands, dtype=np.float64).reshape(-1, 2), tail])
    x, y, yaw, v, w = (float(c) for c in pose[:5])
    a = min(1.0, dt / MOTOR_LAG_S)
    out = np.empty((len(cmds), 2))
    for k, (vr, wr) in enumerate(cmds):
        v += a * (vr - v)
        w += a * (wr - w)
        x += v * np.cos(yaw) * dt
        y += v * np.sin(yaw) * dt
        yaw += w * dt
        out[k] = (x, y)
    return out


class AreaExcitation:
    """`Excitation`'s segments (held commands 2-5 s, ramps, chirps, jitter) that keep the robot inside an `area`.

    Before each segment its path is predicted from the robot's pose (`predict_path`, braking room included); a
    segment that would come closer than `margin` to an edge is drawn again (up to `tries` times), and when none
    fits, or the robot is already in the margin, the segment turns back toward the centre instead: a held turn
    (a loop of radius 0.5 m or less, or on the spot where there is no room for one) until the robot faces the centre,
    then a held straight run toward it. The turns back are steady commands too, so they feed the terrain calibration.

    With `lane_holds` (`Excitation`'s share, off by default: then the stream is as it was) a share of the segments
    are `Excitation.lane_hold`s: a held (v, omega) drives an arc of radius v / omega, kept inside like every segment:
    cut to the longest part that stays `margin` inside (braking room included) as long as that is still a lane hold
    (LANE_HOLD_S[0] or more), else driven the other way round the arc, else drawn again (`tries` times). A lane hold
    that fits nowhere from the robot's pose is tried once more after the turn back toward the centre.
    """

    def __init__(
        self, area: Area, seed: int = 0, dt: float = 0.1, v_max: float = 1.5, w_max: float = np.pi,
        margin: float | None = None, tries: int = 8, lane_holds: float = 0.0,
    ) -> None:
        side = 2.0 * min(area.half_x, area.half_y)
        if not side >= MIN_AREA_M:
            raise ValueError(f"area {2 * area.half_x:g} m x {2 * area.half_y:g} m: each side must be at least "
                             f"{MIN_AREA_M:g} m for the robot to turn and brake inside it; give a larger area")
        if not 0.0 < v_max <= 2.0:
            raise ValueError(f"speed cap {v_max} m/s: must be in (0, 2] m/s")
        self.area = area
        self.dt = dt
        self.v_max = v_max
        self.w_max = w_max
        # 2 m in a 20 m square; a quarter of the side in small areas, so an inner box is left to drive in
        self.margin = float(margin) if margin is not None else min(2.0, 0.25 * side)
        self.tries = tries
        self.base = Excitation(seed=seed, dt=dt, v_max=v_max, w_max=w_max, hold_s=(2.0, 5.0), lane_holds=lane_holds)
        self.rng = self.base.rng
        self.returns = 0  # segments that turned back toward the centre
        self.drawn = 0  # segments of the excitation handed out (the turns back not counted)
        self.lane_held = 0  # ... of which lane holds
        self._lane_due = False  # a lane hold that did not fit: drawn again after the turn back

    @property
    def current(self) -> np.ndarray:
        return self.base.current

    def next_segment(self, pose: np.ndarray) -> np.ndarray:
        """The next (n, 2) commands, from the robot's current pose [X, Y, yaw, v, omega]."""
        pose = np.asarray(pose, dtype=np.float64)
        if self.area.contains(pose[:2], self.margin):
            lane = self._lane_due or self.base.lane_hold_next()
            seg = self._lane_hold(pose) if lane else self._segment(pose)
            if seg is not None:
                self.drawn += 1
                self.lane_held += int(lane)
                self._lane_due = False
                return seg
            # once more from near the centre, so the edges do not thin out the share; then given up (a small area)
            self._lane_due = lane and not self._lane_due
        return self.turn_back(pose)

    def _segment(self, pose: np.ndarray) -> np.ndarray | None:
        """A random segment whose predicted path stays inside, or None."""
        for _ in range(self.tries):
            before = self.base.current.copy()
            seg = self.base.random_segment()
            if self.area.contains(predict_path(pose, seg, self.dt), self.margin):
                return seg
            self.base.current = before
        return None

    def _lane_hold(self, pose: np.ndarray) -> np.ndarray | None:
        """A lane hold, cut or mirrored to stay inside (class docstring), or None."""
        shortest = max(1, int(round(LANE_HOLD_S[0] / self.dt)))
        before = self.base.current.copy()
        for _ in range(self.tries):
            seg = self.base.lane_hold()
            for held in (seg, seg * np.array([1.0, -1.0])):
                n = self._inside_for(pose, held, shortest)
                if n:
                    self.base.current = held[-1].copy()
                    return held[:n]
        self.base.current = before
        return None

    def _inside_for(self, pose: np.ndarray, seg: np.ndarray, shortest: int) -> int:
        """The most leading ticks of `seg`, `shortest` or more, whose path (braking room included) stays inside;
        0 if none."""
        inside = self.area.inside(predict_path(pose, seg, self.dt, tail_s=0.0), self.margin)
        # tick k's command moves the robot to point k: a part of n ticks ends before the first point outside
        n = len(seg) if inside.all() else int(np.argmin(inside))
        for m in range(n, shortest - 1, -1):
            if self.area.contains(predict_path(pose, seg[:m], self.dt), self.margin):
                return m
        return 0

    def heading_out(self, pose: np.ndarray) -> bool:
        """In the margin and moving away from the centre: the robot drifted from its prediction."""
        pose = np.asarray(pose, dtype=np.float64)
        if self.area.contains(pose[:2], self.margin):
            return False
        out = pose[:2] - np.array([self.area.cx, self.area.cy])
        return float(out @ np.array([np.cos(pose[2]), np.sin(pose[2])])) > 0.0

    def turn_back(self, pose: np.ndarray) -> np.ndarray:
        """A held turn to face the centre, then a held straight run toward it."""
        pose = np.asarray(pose, dtype=np.float64)
        self.returns += 1
        to_centre = np.array([self.area.cx, self.area.cy]) - pose[:2]
        err = float(np.angle(np.exp(1j * (np.arctan2(to_centre[1], to_centre[0]) - pose[2]))))
        # room to turn: half the margin stays free even when the loop swings outward
        keep = min(0.5 * self.margin, 1.0)
        turn = np.zeros((0, 2))
        if abs(err) > 0.2:
            w_top = min(self.w_max, 2.5)
            for _ in range(self.tries + 1):
                w = float(np.sign(err) * self.rng.uniform(1.0, w_top))
                v = float(self.rng.uniform(0.0, min(1.0, self.v_max, 0.5 * abs(w))))  # radius v / w <= 0.5 m
                # held a little past the heading change: the lag eats the first part of the turn
                n = max(1, int(np.ceil((abs(err) / abs(w) + MOTOR_LAG_S) / self.dt)))
                turn = np.tile([v, w], (n, 1))
                if self.area.contains(predict_path(pose, turn, self.dt), keep):
                    break
                turn[:, 0] = 0.0  # no room for a loop: turn on the spot
        dist = float(np.hypot(*to_centre))
        # slow enough that 2 s of it end near the centre, not across it (small areas)
        v_hi = min(self.v_max, max(0.5, 0.5 * dist))
        v = float(self.rng.uniform(min(0.5, v_hi), v_hi))
        n = int(np.clip(round(self.rng.uniform(0.5, 1.0) * dist / v / self.dt), round(2.0 / self.dt),
                        round(5.0 / self.dt)))
        seg = np.vstack([turn, np.tile([v, 0.0], (n, 1))])
        self.base.current = seg[-1].copy()
        return seg
