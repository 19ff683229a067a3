"""What the planner is asked to do, as plain arrays: follow a lane, or reach a goal."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gpmppi.costmap import Costmap


@dataclass(frozen=True)
class LaneTask:
    """Follow a lane: a centre polyline (P, 2) [m] with a constant half-width [m]."""

    centerline: np.ndarray
    half_width: float
    speed_target: float = 1.75
    closed: bool = True

    def __post_init__(self) -> None:
        c = np.asarray(self.centerline, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != 2 or c.shape[0] < 2:
            raise ValueError(f"lane centerline must be (P>=2, 2) points, got shape {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError("lane centerline has non-finite points")
        if not (np.isfinite(self.half_width) and self.half_width > 0):
            raise ValueError(f"lane half_width must be a positive number, got {self.half_width}")
        if not (np.isfinite(self.speed_target) and self.speed_target >= 0):
            raise ValueError(f"lane speed_target must be >= 0, got {self.speed_target}")
        object.__setattr__(self, "centerline", np.ascontiguousarray(c))


@dataclass(frozen=True)
class GoalTask:
    """Reach `goal` (2,) within `tolerance` [m] avoiding circles `obstacles` (K, 3) = [x, y, r] and the lethal cells
    of `costmap` (an occupancy grid, or None)."""

    goal: np.ndarray
    tolerance: float = 0.5
    obstacles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    costmap: Costmap | None = None

    def __post_init__(self) -> None:
        g = np.asarray(self.goal, dtype=np.float64).reshape(-1)
        o = np.asarray(self.obstacles, dtype=np.float64).reshape(-1, 3)
        if g.shape != (2,) or not np.all(np.isfinite(g)):
            raise ValueError(f"goal must be 2 finite numbers, got {self.goal!r}")
        if not np.all(np.isfinite(o)) or np.any(o[:, 2] <= 0):
            raise ValueError("obstacles must be finite [x, y, r] rows with r > 0")
        if not (np.isfinite(self.tolerance) and self.tolerance > 0):
            raise ValueError(f"goal tolerance must be > 0, got {self.tolerance}")
        if self.costmap is not None and not isinstance(self.costmap, Costmap):
            raise ValueError(f"costmap must be a gpmppi.costmap.Costmap or None, got {type(self.costmap).__name__}")
        object.__setattr__(self, "goal", g)
        object.__setattr__(self, "obstacles", np.ascontiguousarray(o))


Task = LaneTask | GoalTask


def polyline_segments(centerline: np.ndarray, closed: bool) -> tuple[np.ndarray, np.ndarray]:
    """Segment start points (S, 2) and direction vectors (S, 2) of a polyline (closing it if `closed`)."""
    c = np.asarray(centerline, dtype=np.float64)
    ends = np.roll(c, -1, axis=0) if closed else c[1:]
    starts = c if closed else c[:-1]
    return starts, ends - starts


def distance_to_polyline(points: np.ndarray, centerline: np.ndarray, closed: bool = True) -> np.ndarray:
    """Euclidean distance (T,) from each point (T, 2) to the closest point of the polyline (segments, not vertices)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    starts, dirs = polyline_segments(centerline, closed)
    len2 = np.einsum("sd,sd->s", dirs, dirs)
    len2 = np.where(len2 > 0.0, len2, 1.0)  # a repeated vertex is a zero-length segment: its start is its point
    out = np.empty(p.shape[0])
    chunk = 2048  # bounds the (chunk, S, 2) temporary for long runs over finely sampled lanes
    for i in range(0, p.shape[0], chunk):
        rel = p[i : i + chunk, None, :] - starts[None, :, :]
        t = np.clip(np.einsum("tsd,sd->ts", rel, dirs) / len2, 0.0, 1.0)
        diff = rel - t[..., None] * dirs[None, :, :]
        out[i : i + chunk] = np.sqrt(np.min(np.einsum("tsd,tsd->ts", diff, diff), axis=1))
    return out


def polyline_length(centerline: np.ndarray, closed: bool = True) -> float:
    """Length [m] of a polyline (with its closing segment if `closed`)."""
    _, dirs = polyline_segments(centerline, closed)
    return float(np.sum(np.linalg.norm(dirs, axis=1)))


def progress_along_polyline(points: np.ndarray, centerline: np.ndarray, closed: bool = True) -> np.ndarray:
    """Arc length (T,) [m] from the polyline's first point to the point of it closest to each point (T, 2).

    Ties between equally close segments go to the earliest segment, so a point where an open lane's end meets its
    start counts as the start.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    starts, dirs = polyline_segments(centerline, closed)
    seg_len = np.linalg.norm(dirs, axis=1)
    offset = np.concatenate([[0.0], np.cumsum(seg_len)[:-1]])
    len2 = np.where(seg_len > 0.0, seg_len * seg_len, 1.0)
    out = np.empty(p.shape[0])
    chunk = 2048
    for i in range(0, p.shape[0], chunk):
        rel = p[i : i + chunk, None, :] - starts[None, :, :]
        t = np.clip(np.einsum("tsd,sd->ts", rel, dirs) / len2, 0.0, 1.0)
        diff = rel - t[..., None] * dirs[None, :, :]
        best = np.argmin(np.einsum("tsd,tsd->ts", diff, diff), axis=1)
        rows = np.arange(best.size)
        out[i : i + chunk] = offset[best] + t[rows, best] * seg_len[best]
    return out
