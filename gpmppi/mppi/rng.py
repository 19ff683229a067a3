"""Counter-based Gaussian noise for MPPI: the noise of (seed, iteration, sample, step) is a pure function.

Every sample draws its own noise inside the rollout kernel from a hash of its counter, so the
result does not depend on how threads (CPU) or blocks (CUDA) are scheduled, and the CPU
and CUDA backends draw exactly the same numbers. The hash is SplitMix64's finaliser; one 64-bit
hash gives two 32-bit uniforms, and Box-Muller turns them into the two control-noise normals. Its logarithm, cosine
and sine are polynomials in plain arithmetic (`_log_of_count`, `_cos_sin_of_fraction`), accurate to ~1e-15, not
library calls: a loop over a group of samples then compiles to vector code (the CPU kernel's `_unit_normals`), which
library calls never did (numba's CPU target has no vector math library here).

The CUDA backend compiles the same Python source as device functions
(`gpmppi.gp.cuda_kernels.device_version`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from gpmppi.kernel_flags import fmax, fmin
from gpmppi.trig import nearest, quarter_turned

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_LOW32 = np.uint64(0xFFFFFFFF)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S32 = np.uint64(32)
_LN2 = math.log(2.0)
_SQRT2 = math.sqrt(2.0)
_QUARTER = 1073741824.0  # 2^30: a quarter turn in units of the angle's 32-bit fraction
_RAD_PER_UNIT = 2.0 * math.pi / 4294967296.0  # radians per unit of the angle's 32-bit fraction


@njit(cache=True, inline="always")
def _halved_below(x: float, e: float, p: float, b: float) -> tuple[float, float]:
    """(x / p, e + b) where x >= p = 2^b, else (x, e): an exact step of taking a power of two out of x."""
    big = x >= p
    return (x * (1.0 / p) if big else x), (e + b if big else e)


@njit(cache=True, inline="always")
def _log_of_count(t: float, shift: float) -> float:
    """ln(t / 2^shift) of an integer-valued float t in [1, 2^34) and an integer-valued `shift`, to ~1e-15.

    Branch-free arithmetic (selects and one division), so that a loop over samples compiles to vector code: the power
    of two is taken out by exact halvings, ln of the rest (in [sqrt(2)/2, sqrt(2)]) by the series
    ln x = 2 atanh(s), s = (x - 1) / (x + 1), |s| <= 0.172, whose first omitted term is below 1e-14 of ln x. The
    powers of two are subtracted as integers, before ln 2 multiplies them: ln t - shift ln 2 of t near 2^shift would
    cancel to a few digits."""
    x, e = _halved_below(t, 0.0, 4294967296.0, 32.0)
    x, e = _halved_below(x, e, 65536.0, 16.0)
    x, e = _halved_below(x, e, 256.0, 8.0)
    x, e = _halved_below(x, e, 16.0, 4.0)
    x, e = _halved_below(x, e, 4.0, 2.0)
    x, e = _halved_below(x, e, 2.0, 1.0)
    big = x > _SQRT2  # x in [1, 2): above sqrt(2), halve once more
    x = 0.5 * x if big else x
    e = e + 1.0 if big else e
    s = (x - 1.0) / (x + 1.0)
    s2 = s * s
    series = 1.0 + s2 * (1.0 / 3.0 + s2 * (1.0 / 5.0 + s2 * (1.0 / 7.0 + s2 * (1.0 / 9.0 + s2 * (
        1.0 / 11.0 + s2 * (1.0 / 13.0 + s2 * (1.0 / 15.0 + s2 * (1.0 / 17.0))))))))
    return 2.0 * s * series + (e - shift) * _LN2


@njit(cache=True, inline="always")
def _cos_sin_of_fraction(f: float) -> tuple[float, float]:
    """cos and sin of 2 pi f / 2^32 for an integer-valued float f in [0, 2^32), to ~1e-15.

    The nearest quarter turn q is taken out exactly (f - q 2^30 is an integer below 2^31), the rest (within an eighth of
    a turn) goes to `trig.quarter_turned` (branch-free, as `_log_of_count`)."""
    q = nearest(f * (1.0 / _QUARTER))  # 0 .. 4
    return quarter_turned((f - q * _QUARTER) * _RAD_PER_UNIT, q)  # f - q 2^30 is exact; the angle in [-pi/4, pi/4]


@njit(cache=True, inline="always")
def normal_pair(seed: int, counter: int) -> tuple[float, float]:
    """Two independent standard normals for the 64-bit `counter` under `seed`."""
    # the seed is mixed on its own first so that (seed, counter) pairs never alias each other
    k = np.uint64(seed) * _GOLDEN + _GOLDEN
    k = (k ^ (k >> _S30)) * _MIX1
    k = (k ^ (k >> _S27)) * _MIX2
    k = k ^ (k >> _S31)
    z = k + np.uint64(counter) * _GOLDEN
    z = (z ^ (z >> _S30)) * _MIX1
    z = (z ^ (z >> _S27)) * _MIX2
    z = z ^ (z >> _S31)
    # u1 = (high 32 bits + 1/2) / 2^32 = t / 2^33 with t = 2 high + 1, in (0, 1): its log is finite and below 0;
    # the angle is 2 pi (low 32 bits) / 2^32
    t = 2.0 * float(z >> _S32) + 1.0
    r = math.sqrt(-2.0 * _log_of_count(t, 33.0))
    c, s = _cos_sin_of_fraction(float(z & _LOW32))
    return r * c, r * s


@njit(cache=True, inline="always")
def clip(x: float, lo: float, hi: float) -> float:
    """min(max(x, lo), hi)."""
    return fmin(fmax(x, lo), hi)


@njit(cache=True, inline="always")
def rate_limited(u0: float, u1: float, u_prev: np.ndarray, rate_step: np.ndarray) -> tuple[float, float]:
    """(u0, u1) within `rate_step` [m/s, rad/s] of the command `u_prev` before it; inf: unlimited (the same bits)."""
    return (clip(u0, u_prev[0] - rate_step[0], u_prev[0] + rate_step[0]),
            clip(u1, u_prev[1] - rate_step[1], u_prev[1] + rate_step[1]))


@njit(cache=True, inline="always")
def sampled_command(
    seed: int, counter: int, nominal: np.ndarray, k: int, noise_std: np.ndarray, u_lo: np.ndarray, u_hi: np.ndarray,
    ar: tuple, d0: float, d1: float, first_step: tuple,
) -> tuple[float, float, float, float]:
    """Step k's command of one sample and its unit noise (d0, d1), given the sample's unit noise of step k - 1.

    `ar` = (memory, innovation): the noise is AR(1), d_k = memory d_{k-1} + innovation z_k with innovation =
    sqrt(1 - memory^2) and d_0 = z_0, so each step's noise stays N(0, 1) and steps tau apart correlate by
    memory^(tau / dt) (time-correlated, "coloured" noise). memory = 0 is white noise, d_k = z_k. The command is
    nominal + noise_std * d, clipped to the limits; step 0's then to within `rate_step` of `u_prev`, the command
    in effect (`first_step` = (u_prev, rate_step), each (2,) [m/s, rad/s]; inf: no limit, the same bits). So every
    sample's first command, the update's first command (their weighted average) and the command sent change from
    the one before by at most the rate limits allow in a step. The later steps stay free: limited too, the samples
    became random walks of the limit's size, the time-correlated exploration that tracked worse
    (docs/smooth_commands.md), and the next plan limits its own first command anyway."""
    z0, z1 = normal_pair(seed, counter)
    return command_from_normals(z0, z1, nominal, k, noise_std, u_lo, u_hi, ar, d0, d1, first_step)


@njit(cache=True, inline="always")
def command_from_normals(
    z0: float, z1: float, nominal: np.ndarray, k: int, noise_std: np.ndarray, u_lo: np.ndarray, u_hi: np.ndarray,
    ar: tuple, d0: float, d1: float, first_step: tuple,
) -> tuple[float, float, float, float]:
    """`sampled_command` given the step's two standard normals (z0, z1) = `normal_pair(seed, counter)`: the CPU
    kernel draws a group's normals in a loop of their own (vector code) and then makes the commands with this."""
    memory, innovation = ar
    if memory > 0.0 and k > 0:
        z0 = memory * d0 + innovation * z0
        z1 = memory * d1 + innovation * z1
    u0 = clip(nominal[k, 0] + noise_std[0] * z0, u_lo[0], u_hi[0])
    u1 = clip(nominal[k, 1] + noise_std[1] * z1, u_lo[1], u_hi[1])
    if k == 0:  # within the box still: the window is around a command inside it
        u0, u1 = rate_limited(u0, u1, first_step[0], first_step[1])
    return u0, u1, z0, z1


def noise_memory(correlation_time: float, dt: float) -> float:
    """The AR(1) memory exp(-dt / correlation_time) of noise whose correlation falls by 1/e in `correlation_time`
    [s]; 0 (white noise) for a correlation time of 0."""
    return math.exp(-dt / correlation_time) if correlation_time > 0.0 else 0.0


def noise_counter(iteration: int, sample: int, step: int, samples: int, horizon: int) -> int:
    """The counter of (iteration, sample, step); the kernels compute the same expression inline."""
    return (iteration * samples + sample) * horizon + step


@njit(cache=True)
def standard_noise(seed: int, iteration: int, samples: int, horizon: int) -> np.ndarray:
    """The (samples, horizon, 2) standard normals the kernels draw for one iteration (for tests)."""
    out = np.empty((samples, horizon, 2))
    for s in range(samples):
        for k in range(horizon):
            a, b = normal_pair(seed, (iteration * samples + s) * horizon + k)
            out[s, k, 0] = a
            out[s, k, 1] = b
    return out


def sampled_noise(seed: int, iteration: int, samples: int, horizon: int, memory: float) -> np.ndarray:
    """The (samples, horizon, 2) unit noise d of `sampled_command` for one iteration, in numpy (the kernels'
    reference, for tests): white for memory 0, else AR(1) over the steps."""
    z = standard_noise(seed, iteration, samples, horizon)
    innovation = np.sqrt(1.0 - memory * memory)
    d = z.copy()
    for k in range(1, horizon):
        d[:, k] = memory * d[:, k - 1] + innovation * z[:, k] if memory > 0.0 else z[:, k]
    return d
