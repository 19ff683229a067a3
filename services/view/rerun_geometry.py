"""Pure geometry and colour helpers of the rerun view (numpy only): circles, covariance ellipses, lane offsets,
the tightened lane along the plan horizon, the robot's outline, and a cost colour ramp."""

from __future__ import annotations

import numpy as np

# the robot drawn as a footprint with a pointed nose (so its heading reads at a glance), body frame [m]:
# about a Jackal's 0.51 m x 0.43 m
ROBOT_OUTLINE = np.array([[-0.25, -0.215], [0.17, -0.215], [0.32, 0.0], [0.17, 0.215], [-0.25, 0.215], [-0.25, -0.215]])

# cost ramp, low -> high: teal, yellow, red (RGBA; rollouts are drawn half-transparent so the plan shows through)
_RAMP = np.array([[20, 170, 150, 150], [235, 200, 40, 130], [215, 50, 50, 110]], dtype=np.float64)


def circle(x: float, y: float, r: float, n: int = 48) -> np.ndarray:
    """(n+1) x 2 closed polyline of a circle of radius r [m] about (x, y)."""
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    return np.stack([x + r * np.cos(a), y + r * np.sin(a)], axis=1)


def ellipse(cx: float, cy: float, sxx: float, sxy: float, syy: float, n_sigma: float = 2.0, n: int = 16) -> np.ndarray:
    """Closed polyline of the n_sigma ellipse of a 2-D position covariance [m^2] about (cx, cy)."""
    cov = np.array([[sxx, sxy], [sxy, syy]])
    vals, vecs = np.linalg.eigh(cov)
    vals = np.clip(vals, 0.0, None)
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    unit = np.stack([np.cos(a), np.sin(a)], axis=1)
    return np.array([cx, cy]) + n_sigma * (unit * np.sqrt(vals)) @ vecs.T


def ellipses(centres: np.ndarray, covs: np.ndarray, n_sigma: float = 2.0, n: int = 16) -> np.ndarray:
    """K x (n+1) x 2 closed polylines of the n_sigma ellipses of K position covariances [sxx, sxy, syy] [m^2]
    about K centres (a 2 x 2 eigen-decomposition in closed form, for all at once)."""
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    sxx, sxy, syy = np.asarray(covs, dtype=np.float64).reshape(-1, 3).T
    mean, diff = (sxx + syy) / 2, np.sqrt(((sxx - syy) / 2) ** 2 + sxy**2)
    l1, l2 = np.clip(mean + diff, 0.0, None), np.clip(mean - diff, 0.0, None)
    angle = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # of the major axis
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    u, v = n_sigma * np.sqrt(l1)[:, None] * np.cos(a), n_sigma * np.sqrt(l2)[:, None] * np.sin(a)
    ca, sa = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return np.stack([c[:, :1] + u * ca - v * sa, c[:, 1:] + u * sa + v * ca], axis=2)


def offset(polyline: np.ndarray, distance: np.ndarray | float, closed: bool) -> np.ndarray:
    """The polyline shifted left by `distance` [m] (per vertex or constant) along its normals (closed: the first
    point is repeated at the end)."""
    p = np.asarray(polyline, dtype=np.float64)
    nxt = np.roll(p, -1, axis=0) if closed else np.vstack([p[1:], 2 * p[-1] - p[-2]])
    prv = np.roll(p, 1, axis=0) if closed else np.vstack([2 * p[0] - p[1], p[:-1]])
    t = nxt - prv
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    normal = np.stack([-t[:, 1], t[:, 0]], axis=1)
    out = p + normal * np.reshape(distance, (-1, 1))
    return np.vstack([out, out[:1]]) if closed else out


def closed_polyline(points: np.ndarray, closed: bool) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    return np.vstack([p, p[:1]]) if closed else p


def project_to_lane(points: np.ndarray, centerline: np.ndarray, closed: bool) -> tuple[np.ndarray, np.ndarray]:
    """For each point, its nearest point on the centre polyline and the lane's left unit normal there (searched
    on the two segments next to the nearest vertex: exact for lanes whose turns are wider than the lane)."""
    c = np.asarray(centerline, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    m = len(c)
    d2 = ((p[:, None, :] - c[None]) ** 2).sum(axis=2)  # P x M
    v = np.argmin(d2, axis=1)
    starts = np.stack([v - 1, v], axis=1)  # the segments ending and starting at the nearest vertex
    starts = starts % m if closed else np.clip(starts, 0, m - 2)
    a, b = c[starts], c[(starts + 1) % m]  # P x 2 x 2
    seg = b - a
    seg_len2 = np.maximum((seg**2).sum(axis=2), 1e-12)
    t = np.clip(((p[:, None, :] - a) * seg).sum(axis=2) / seg_len2, 0.0, 1.0)
    foot = a + t[..., None] * seg
    best = np.argmin(((foot - p[:, None, :]) ** 2).sum(axis=2), axis=1)
    rows = np.arange(len(p))
    tangent = seg[rows, best] / np.sqrt(seg_len2[rows, best])[:, None]
    return foot[rows, best], np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)


def tightened_bounds(
    states_xy: np.ndarray, half_widths: np.ndarray, centerline: np.ndarray, closed: bool
) -> list[np.ndarray]:
    """The tightened lane bounds where the plan uses them: at each plan step's nearest centre point, the
    tightened half-width [m] to either side (two polylines, left and right)."""
    n = min(len(states_xy), len(half_widths))
    if n < 2:
        return []
    foot, normal = project_to_lane(np.asarray(states_xy)[:n], centerline, closed)
    r = np.asarray(half_widths, dtype=np.float64)[:n, None]
    return [foot + normal * r, foot - normal * r]


def robot_outline(x: float, y: float, theta: float) -> np.ndarray:
    """The robot's outline in the map frame at pose (x, y, theta)."""
    c, s = np.cos(theta), np.sin(theta)
    rot = np.array([[c, -s], [s, c]])
    return ROBOT_OUTLINE @ rot.T + np.array([x, y])


def cost_colors(costs: np.ndarray) -> np.ndarray:
    """RGBA per rollout by cost rank (rank, not value: costs span decades once an indicator term fires)."""
    costs = np.asarray(costs, dtype=np.float64)
    n = costs.size
    if n == 0:
        return np.zeros((0, 4), dtype=np.uint8)
    finite = np.where(np.isfinite(costs), costs, np.inf)
    u = np.empty(n)
    u[np.argsort(finite, kind="stable")] = np.linspace(0.0, 1.0, n) if n > 1 else [0.0]
    x = u * (len(_RAMP) - 1)
    i = np.minimum(x.astype(int), len(_RAMP) - 2)
    f = (x - i)[:, None]
    return np.round(_RAMP[i] * (1 - f) + _RAMP[i + 1] * f).astype(np.uint8)


def pack_rgba(colors: np.ndarray) -> np.ndarray:
    """N x 4 uint8 RGBA as N packed 0xRRGGBBAA uint32 (rerun takes these without conversion)."""
    c = np.asarray(colors, dtype=np.uint32)
    return (c[:, 0] << 24) | (c[:, 1] << 16) | (c[:, 2] << 8) | c[:, 3]
