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
    """For each point, its nearest point on the centre polyline and the lane's left unit normal there."""
    c = np.asarray(centerline, dtype=np.float64)
    a = c if closed else c[:-1]
    b = np.roll(c, -1, axis=0) if closed else c[1:]
    seg = b - a  # S x 2
    seg_len2 = np.maximum(np.einsum("ij,ij->i", seg, seg), 1e-12)
    p = np.asarray(points, dtype=np.float64)[:, None, :]  # P x 1 x 2
    t = np.clip(np.einsum("psk,sk->ps", p - a[None], seg) / seg_len2[None], 0.0, 1.0)  # P x S
    foot = a[None] + t[..., None] * seg[None]  # P x S x 2
    d2 = np.einsum("psk,psk->ps", foot - p, foot - p)
    best = np.argmin(d2, axis=1)
    rows = np.arange(p.shape[0])
    tangent = seg[best] / np.sqrt(seg_len2[best])[:, None]
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    return foot[rows, best], normal


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
