"""How much the lane RMSE of one window varies against the window before it when nothing happens: the reference
against which a takeover's "RMSE over the 5 s after / the 5 s before" is judged (`gpmppi bench startup`).

On the simulated circle lane single 5 s windows vary from about 8 to 19 mm while the robot just drives, so the
ratio of two consecutive windows passes 1.5 now and then with no fault at all; a takeover's ratio means something
only beside the same ratio taken where there was no kill. Pure: arrays in, numbers out.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gpmppi.tasks import distance_to_polyline


def window_rmse_mm(stamps_ns: np.ndarray, distance_m: np.ndarray, t0_ns: int, t1_ns: int,
                   min_points: int = 5) -> float | None:
    """RMSE [mm] of the distances to the centre line stamped in [t0, t1); None with fewer than `min_points`."""
    d = distance_m[(stamps_ns >= t0_ns) & (stamps_ns < t1_ns)]
    return None if d.size < min_points else float(np.sqrt(np.mean(d * d)) * 1e3)


def consecutive_window_ratios(
    stamps_ns: Sequence[int] | np.ndarray, xy: np.ndarray, centerline: np.ndarray, closed: bool,
    excluded: Sequence[tuple[int, int]] = (), window_s: float = 5.0, step_s: float = 1.0,
) -> np.ndarray:
    """RMSE over `window_s` after a boundary / over `window_s` before it, for boundaries every `step_s` along the
    states (stamps [ns], positions (n, 2) [m]) whose two windows overlap none of the `excluded` intervals [ns]
    (the kills and what followed them)."""
    t = np.asarray(stamps_ns, dtype=np.int64)
    order = np.argsort(t, kind="stable")
    t = t[order]
    d = distance_to_polyline(np.asarray(xy, dtype=np.float64).reshape(-1, 2)[order], np.asarray(centerline), closed)
    w, step = int(window_s * 1e9), int(step_s * 1e9)
    ratios = []
    if t.size == 0:
        return np.zeros(0)
    for c in range(int(t[0]) + w, int(t[-1]) - w + 1, step):
        if any(c - w < b and a < c + w for a, b in excluded):
            continue
        before = window_rmse_mm(t, d, c - w, c)
        after = window_rmse_mm(t, d, c, c + w)
        if before and after is not None:
            ratios.append(after / before)
    return np.array(ratios)


def ratio_summary(ratios: np.ndarray, limit: float = 1.5) -> dict[str, float | int | None]:
    """n, p50, p95, max of the ratios, and the share of them above `limit`."""
    if ratios.size == 0:
        return {"n": 0, "p50": None, "p95": None, "max": None, "share_over_limit": None, "limit": limit}
    return {
        "n": int(ratios.size),
        "p50": round(float(np.percentile(ratios, 50)), 2),
        "p95": round(float(np.percentile(ratios, 95)), 2),
        "max": round(float(ratios.max()), 2),
        "share_over_limit": round(float(np.mean(ratios > limit)), 3),
        "limit": limit,
    }
