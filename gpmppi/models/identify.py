"""Parameter identification: the nominal dynamic unicycle (theta) and the EDD5 kinematic model.

Sampling convention (the dataset's): `v[k], w[k]` are measured at t_k and the command
`v_ref[k], w_ref[k]` is applied over [t_k, t_k + dt). Data may come in several segments (a list of
arrays, or one array plus a segment-id array); nothing is ever differenced across a segment gap.

theta. The nominal model

    vdot = (th3/th1) w^2 - (th4/th1) v + v_ref/th1,     wdot = -(th5/th2) v w - (th6/th2) w + w_ref/th2

is linear in (1/th1, th3/th1, th4/th1) and (1/th2, th5/th2, th6/th2). Normalization: we regress the
measured derivative on the regressors (`vdot = a w^2 - b v + c v_ref`), so the noisy quantity is the
dependent variable and the command (exact, noise free) is a regressor, then map back
`th1 = 1/c, th3 = a/c, th4 = b/c` (well posed while the input gain c is bounded away from zero, which
any excited data guarantees). The derivative over each sampling interval is the difference quotient,
paired with interval means of the regressors (trapezoid), because the command is constant exactly over
that interval. Optional Savitzky-Golay smoothing per segment (`smooth_window`) helps high-rate noisy
data; at dt = 0.1 s it blurs responses whose time constants are ~0.2 s and biases them (by ~25% with a
5-sample window on nominal-model data), so it is off by default. With `refine`
(default) the linear estimate then seeds a nonlinear least-squares fit of the one-step prediction
error of `velocity_step_exact`, which is precisely the residual the GP learns, so it removes the
discretization bias of the difference quotient.

EDD5. `identify_edd5` fits `[alpha_r, alpha_l, x_v, y_r, y_l]` to measured (v, omega) by robust least
squares (soft-L1 loss). `x_v` does not enter v or omega: it is kept at its initial value unless the
body lateral velocity is given (EDD5: `v_y = -x_v omega`), in which case it is fitted too.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gpmppi.models.dynamic_unicycle import velocity_step_exact
from gpmppi.models.edd5 import TRACK_B, WHEEL_R

ArrayOrSegments = np.ndarray | Sequence[np.ndarray]

EDD5_INITIAL = np.array([0.9, 0.9, 0.0, -0.25, 0.25])  # symmetric guess: mild slip, ICRs just outside the wheels


def _split(x: ArrayOrSegments, segment_ids: np.ndarray | None, name: str) -> list[np.ndarray]:
    if isinstance(x, np.ndarray) and x.ndim == 1:
        if segment_ids is None:
            return [x.astype(float)]
        ids = np.asarray(segment_ids)
        if ids.shape != x.shape:
            raise ValueError(f"segment_ids has shape {ids.shape} but {name} has shape {x.shape}")
        cuts = np.flatnonzero(np.diff(ids) != 0) + 1
        return [s.astype(float) for s in np.split(x, cuts)]
    if segment_ids is not None:
        raise ValueError(f"{name}: give either a list of segments or one array with segment_ids, not both")
    return [np.asarray(s, dtype=float).ravel() for s in x]


def one_step_pairs(
    v: ArrayOrSegments,
    w: ArrayOrSegments,
    v_ref: ArrayOrSegments,
    w_ref: ArrayOrSegments,
    segment_ids: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(v_k, w_k, v_ref_k, w_ref_k, v_{k+1}, w_{k+1}) over all within-segment transitions."""
    parts = [_split(a, segment_ids, n) for a, n in ((v, "v"), (w, "w"), (v_ref, "v_ref"), (w_ref, "w_ref"))]
    if len({len(p) for p in parts}) != 1:
        raise ValueError(f"v, w, v_ref, w_ref have different segment counts {[len(p) for p in parts]}")
    out: list[list[np.ndarray]] = [[] for _ in range(6)]
    for sv, sw, sr, sq in zip(*parts, strict=True):
        if not (len(sv) == len(sw) == len(sr) == len(sq)):
            raise ValueError(f"a segment has mismatched lengths v {len(sv)}, w {len(sw)}, cmd {len(sr)}/{len(sq)}")
        if len(sv) < 2:
            continue
        for lst, arr in zip(out, (sv[:-1], sw[:-1], sr[:-1], sq[:-1], sv[1:], sw[1:]), strict=True):
            lst.append(arr)
    if not out[0]:
        raise ValueError("no segment has two or more samples: nothing to identify from")
    return tuple(np.concatenate(lst) for lst in out)  # type: ignore[return-value]


def _smooth(x: np.ndarray, window: int) -> np.ndarray:
    """Savitzky-Golay (quadratic) smoothing; windows below 3 or longer than the segment leave it as is."""
    if window < 3 or len(x) < window:
        return x
    from scipy.signal import savgol_filter  # here: scipy.signal costs ~0.35 s to import, and every CLI start paid it

    return savgol_filter(x, window, min(3, window - 1), mode="interp")


def identify_theta(
    v: ArrayOrSegments,
    w: ArrayOrSegments,
    v_ref: ArrayOrSegments,
    w_ref: ArrayOrSegments,
    dt: float,
    segment_ids: np.ndarray | None = None,
    smooth_window: int = 0,
    refine: bool = True,
    max_refine_points: int = 20000,
    seed: int = 0,
) -> np.ndarray:
    """Least-squares theta (6,) of the nominal dynamic unicycle from measured velocities and commands."""
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt}")
    sv, sw, sr, sq = (_split(a, segment_ids, n) for a, n in ((v, "v"), (w, "w"), (v_ref, "v_ref"), (w_ref, "w_ref")))
    rows_v: list[np.ndarray] = []
    rows_w: list[np.ndarray] = []
    ys_v: list[np.ndarray] = []
    ys_w: list[np.ndarray] = []
    for a, b, cv, cw in zip(sv, sw, sr, sq, strict=True):
        if len(a) < 2:
            continue
        fa, fb = _smooth(a, smooth_window), _smooth(b, smooth_window)
        mean_v = 0.5 * (fa[:-1] + fa[1:])
        mean_w = 0.5 * (fb[:-1] + fb[1:])
        mean_w2 = 0.5 * (fb[:-1] ** 2 + fb[1:] ** 2)
        mean_vw = 0.5 * (fa[:-1] * fb[:-1] + fa[1:] * fb[1:])
        ys_v.append(np.diff(fa) / dt)
        ys_w.append(np.diff(fb) / dt)
        rows_v.append(np.column_stack([mean_w2, -mean_v, cv[:-1]]))
        rows_w.append(np.column_stack([-mean_vw, -mean_w, cw[:-1]]))
    if not rows_v:
        raise ValueError("no segment has two or more samples: nothing to identify from")
    (a_v, b_v, c_v), *_ = np.linalg.lstsq(np.vstack(rows_v), np.concatenate(ys_v), rcond=None)
    (a_w, b_w, c_w), *_ = np.linalg.lstsq(np.vstack(rows_w), np.concatenate(ys_w), rcond=None)
    if c_v <= 1e-6 or c_w <= 1e-6:
        raise ValueError(
            f"the data do not excite the command gains (1/th1 = {c_v:.3g}, 1/th2 = {c_w:.3g}); "
            "drive with varied v_ref and omega_ref"
        )
    theta = np.array([1.0 / c_v, 1.0 / c_w, a_v / c_v, b_v / c_v, a_w / c_w, b_w / c_w])
    if not refine:
        return theta
    return refine_theta(theta, *one_step_pairs(v, w, v_ref, w_ref, segment_ids), dt, max_refine_points, seed)


def refine_theta(
    theta0: np.ndarray,
    v: np.ndarray,
    w: np.ndarray,
    v_ref: np.ndarray,
    w_ref: np.ndarray,
    v_next: np.ndarray,
    w_next: np.ndarray,
    dt: float,
    max_points: int = 20000,
    seed: int = 0,
) -> np.ndarray:
    """Theta minimizing the one-step prediction error of `velocity_step_exact` (least squares, from theta0)."""
    n = len(v)
    if n > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))
        v, w, v_ref, w_ref, v_next, w_next = (a[idx] for a in (v, w, v_ref, w_ref, v_next, w_next))

    def residual(th: np.ndarray) -> np.ndarray:
        pv, pw = velocity_step_exact(th, v, w, v_ref, w_ref, dt)
        return np.concatenate([pv - v_next, pw - w_next])

    lower = np.array([1e-3, 1e-3, -np.inf, -np.inf, -np.inf, -np.inf])
    start = np.maximum(np.asarray(theta0, dtype=float), lower + 1e-3)
    from scipy.optimize import least_squares

    sol = least_squares(residual, start, bounds=(lower, np.full(6, np.inf)), x_scale="jac")
    return sol.x


def identify_edd5(
    v_ref: np.ndarray,
    w_ref: np.ndarray,
    v_meas: np.ndarray,
    w_meas: np.ndarray,
    lateral_meas: np.ndarray | None = None,
    initial: np.ndarray | None = None,
    max_points: int = 300,
    seed: int = 0,
) -> np.ndarray:
    """Robust (soft-L1) least-squares EDD5 parameters (5,) `[alpha_r, alpha_l, x_v, y_r, y_l]`.

    Uses at most `max_points` samples (a seeded random subset). `x_v` stays at its initial value
    unless `lateral_meas` (body lateral velocity) is given.
    """
    arrays = [np.asarray(a, dtype=float).ravel() for a in (v_ref, w_ref, v_meas, w_meas)]
    if lateral_meas is not None:
        arrays.append(np.asarray(lateral_meas, dtype=float).ravel())
    if len({len(a) for a in arrays}) != 1:
        raise ValueError(f"identify_edd5: inputs have different lengths {[len(a) for a in arrays]}")
    if len(arrays[0]) < 4:
        raise ValueError("identify_edd5 needs at least 4 samples")
    n = len(arrays[0])
    if n > max_points:
        idx = np.random.default_rng(seed).choice(n, max_points, replace=False)
        arrays = [a[idx] for a in arrays]
    cv, cw, mv, mw = arrays[:4]
    lat = arrays[4] if lateral_meas is not None else None
    p0 = EDD5_INITIAL.copy() if initial is None else np.asarray(initial, dtype=float).copy()
    wheel_r = (cv + 0.5 * cw * TRACK_B) / WHEEL_R
    wheel_l = (cv - 0.5 * cw * TRACK_B) / WHEEL_R

    def full(q: np.ndarray) -> np.ndarray:
        p = p0.copy()
        p[[0, 1, 3, 4]] = q[:4]
        if lat is not None:
            p[2] = q[4]
        return p

    def residual(q: np.ndarray) -> np.ndarray:
        p = full(q)
        k = WHEEL_R / (p[4] - p[3])
        pv = k * (-p[3] * p[1] * wheel_l + p[4] * p[0] * wheel_r)
        pw = k * (-p[1] * wheel_l + p[0] * wheel_r)
        res = [pv - mv, pw - mw]
        if lat is not None:
            res.append(-p[2] * pw - lat)
        return np.concatenate(res)

    q0 = p0[[0, 1, 3, 4]] if lat is None else p0[[0, 1, 3, 4, 2]]
    # y_r < 0 < y_l keeps the ICR ordering (right ICR on the right) and the model non-singular
    lower = np.array([1e-3, 1e-3, -5.0, 1e-3] + ([-5.0] if lat is not None else []))
    upper = np.array([5.0, 5.0, -1e-3, 5.0] + ([5.0] if lat is not None else []))
    from scipy.optimize import least_squares

    sol = least_squares(residual, np.clip(q0, lower + 1e-6, upper - 1e-6), bounds=(lower, upper),
                        loss="soft_l1", f_scale=0.05)
    return full(sol.x)
