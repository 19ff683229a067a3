"""The Savitzky-Golay smoother's matrix, without importing scipy.signal.

`scipy.signal.savgol_filter(u, window, order, axis=0, mode="nearest")` is linear in u, so the planner applies it as
one (horizon, horizon) matrix made once: the filter of the identity's columns. Importing scipy.signal for that cost
every planner start ~0.6-0.9 s of CPU (it imports scipy.stats), more than the rest of scipy the planner uses. The
filter is two steps, done here as scipy does them, operation for operation, so the matrix has the same bits
(tests/test_savgol.py compares them with scipy's over the windows, orders and horizons the settings allow):

1. the coefficients (`scipy.signal.savgol_coeffs(window, order)`): the least-squares solution, by
   `scipy.linalg.lstsq`, of a Vandermonde system over the window's offsets;
2. their convolution along the horizon with the ends held (`scipy.ndimage.convolve1d(..., mode="nearest")`):
   a correlation with the reversed coefficients, summed in the order scipy.ndimage's C loop sums (the centre
   first, then the pairs from the outermost in; a symmetric filter adds each pair before weighting it). The inputs
   are the identity's 0s and 1s, so every product is exact and only that order decides the bits.
"""

from __future__ import annotations

import numpy as np

DBL_EPSILON = float(np.finfo(np.float64).eps)


def savgol_coeffs(window: int, order: int) -> np.ndarray:
    """`scipy.signal.savgol_coeffs(window, order)` (odd window, no derivative, ordered for a convolution)."""
    # scipy.linalg, not scipy.signal: the planner's process has most of what it imports already (scipy.special)
    from scipy.linalg import lstsq

    if window % 2 != 1 or not 0 <= order < window:
        raise ValueError(f"a Savitzky-Golay window must be odd and larger than the order, got {window} and {order}")
    pos = window // 2
    # the same arrays as scipy builds (a flipped view, then a broadcast power), so the same numpy loops run
    x = np.flip(np.arange(-pos, window - pos, dtype=np.float64))
    powers = np.reshape(np.arange(order + 1, dtype=np.float64), (-1, 1))
    a = x**powers
    y = np.zeros(order + 1, dtype=np.float64)
    y[0] = 1.0
    coeffs, _, _, _ = lstsq(a, y, cond=DBL_EPSILON * max(a.shape[-1], a.shape[-2]))
    return np.asarray(coeffs)


def savgol_matrix(horizon: int, window: int, order: int) -> np.ndarray:
    """The (horizon, horizon) matrix M with M @ u = scipy's `savgol_filter(u, window, order, axis=0,
    mode="nearest")`, to the bit: that filter of the identity."""
    if not 1 <= window <= horizon:
        raise ValueError(f"a Savitzky-Golay window must be within the horizon ({horizon}), got {window}")
    fw = np.ascontiguousarray(savgol_coeffs(window, order)[::-1], dtype=np.float64)  # correlation weights
    half = window // 2
    eye = np.eye(horizon)
    # mode "nearest": the line extended by its first and last values
    line = np.concatenate([np.repeat(eye[:1], half, axis=0), eye, np.repeat(eye[-1:], half, axis=0)])

    def at(offset: int) -> np.ndarray:  # the extended line shifted by `offset` taps, for every output row
        return line[half + offset:half + offset + horizon]

    # scipy.ndimage's test: symmetric or antisymmetric within DBL_EPSILON (NaN counts as within)
    pairs = range(1, half + 1)
    if not any(abs(fw[half + k] - fw[half - k]) > DBL_EPSILON for k in pairs):
        sign = 1.0
    elif not any(abs(fw[half + k] + fw[half - k]) > DBL_EPSILON for k in pairs):
        sign = -1.0
    else:
        sign = 0.0
    if sign != 0.0:
        out = at(0) * fw[half]
        for k in range(half, 0, -1):
            pair = at(-k) + at(k) if sign > 0 else at(-k) - at(k)
            out += pair * fw[half - k]
    else:
        out = at(half) * fw[2 * half]
        for k in range(-half, half):
            out += at(k) * fw[half + k]
    return np.ascontiguousarray(out)
