"""cos and sin for the planner kernels: polynomials in plain arithmetic, to ~1e-15, without library calls.

The C library's `sincos` was a fifth of the planner's CPU time (the lane speed critic's heading, the model's pose
step, every sample-step; docs/benchmarks.md): a call that no loop around it can vectorise, and slow for the large
unwrapped headings of a robot that has turned many times. Here an angle is reduced by the nearest quarter turn with
pi/2 in three parts (Cody and Waite: each product with the quarter-turn count is exact or nearly so), the rest
(within an eighth of a turn) goes through Taylor polynomials, and selects turn the pair back. The same Python runs as
CUDA device functions (`gpmppi.gp.cuda_kernels.device_version`).
"""

from __future__ import annotations

import math

from numba import njit

__all__ = ["cos_sin", "nearest", "quarter_turned"]

# pi/2 in three parts, fdlibm's: the first two have 33 significant bits, so q * part is exact for |q| < 2^20
_PIO2_1 = 1.57079632673412561417e00
_PIO2_2 = 6.07710050630396597660e-11
_PIO2_3 = 2.02226624879595063154e-21
_TWO_OVER_PI = 2.0 / math.pi
_ROUNDER = 6755399441055744.0  # 1.5 * 2^52: (y + it) - it is y rounded to the nearest integer, for |y| < 2^51


@njit(cache=True, inline="always")
def nearest(y: float) -> float:
    """y rounded to the nearest integer (ties to even), as a float, for |y| < 2^51; NaN and infinities stay so.

    Two additions, where `math.floor` gives an int64 (undefined for a non-finite y) and numba converts it back, and
    the kernels' flags never let the compiler regroup (y + c) - c into y (no `reassoc`: gpmppi.kernel_flags)."""
    return (y + _ROUNDER) - _ROUNDER


@njit(cache=True, inline="always")
def quarter_turned(a: float, q: float) -> tuple[float, float]:
    """cos and sin of a + q pi/2 for |a| <= pi/4 and an integer-valued q (any sign), to ~1e-15.

    Taylor polynomials to a^16 and a^17 (their first omitted terms are below 1e-15 at pi/4), then the pair is turned
    by q mod 4 quarter turns with selects, no branches."""
    a2 = a * a
    c = 1.0 + a2 * (-1.0 / 2.0 + a2 * (1.0 / 24.0 + a2 * (-1.0 / 720.0 + a2 * (1.0 / 40320.0 + a2 * (
        -1.0 / 3628800.0 + a2 * (1.0 / 479001600.0 + a2 * (-1.0 / 87178291200.0)))))))
    s = a * (1.0 + a2 * (-1.0 / 6.0 + a2 * (1.0 / 120.0 + a2 * (-1.0 / 5040.0 + a2 * (1.0 / 362880.0 + a2 * (
        -1.0 / 39916800.0 + a2 * (1.0 / 6227020800.0 + a2 * (-1.0 / 1307674368000.0))))))))
    turn = q - 4.0 * nearest(0.25 * q - 0.375)  # q mod 4, in 0 .. 3 for negative q too
    odd = turn == 1.0 or turn == 3.0  # a quarter or three: cos and sin trade places
    c1 = s if odd else c
    s1 = c if odd else s
    return (-c1 if turn == 1.0 or turn == 2.0 else c1), (-s1 if turn == 2.0 or turn == 3.0 else s1)


@njit(cache=True, inline="always")
def cos_sin(x: float) -> tuple[float, float]:
    """cos x and sin x of a finite angle [rad], to ~1e-15 absolute for |x| < 1e5 (a heading after ~16,000 turns);
    a non-finite x gives NaN for both, as the library's."""
    q = nearest(x * _TWO_OVER_PI)  # the nearest quarter turn
    a = ((x - q * _PIO2_1) - q * _PIO2_2) - q * _PIO2_3  # in [-pi/4, pi/4] (to rounding)
    return quarter_turned(a, q)
