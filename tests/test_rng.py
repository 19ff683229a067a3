"""The counter-based noise (`gpmppi.mppi.rng.normal_pair`) against an independent reference and scipy's normal.

The reference is written here in numpy: SplitMix64's finaliser on the counter, then Box-Muller with numpy's own
float64 log, cos and sin. The generator computes those by polynomials (so that the CPU kernel's loop over a group of
samples is vector code); they must agree to ~1e-15 relative, and the kernel must draw exactly the generator's numbers.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from gpmppi.mppi.rng import normal_pair, standard_noise

_MASK = (1 << 64) - 1
_GOLDEN = 0x9E3779B97F4A7C15


def _mix(z: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser on uint64 values (numpy's uint64 arithmetic wraps modulo 2^64)."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def _reference_pairs(seed: int, counters: np.ndarray) -> np.ndarray:
    """(n, 2) normals of `counters` under `seed`: the generator's hash, and Box-Muller in numpy's float64."""
    with np.errstate(over="ignore"):
        k = _mix(np.array([(seed * _GOLDEN + _GOLDEN) & _MASK], dtype=np.uint64))[0]
        z = _mix(k + counters.astype(np.uint64) * np.uint64(_GOLDEN))
    u1 = ((z >> np.uint64(32)).astype(np.float64) + 0.5) / 2.0**32
    u2 = (z & np.uint64(0xFFFFFFFF)).astype(np.float64) / 2.0**32
    r = np.sqrt(-2.0 * np.log(u1))
    return np.stack([r * np.cos(2.0 * np.pi * u2), r * np.sin(2.0 * np.pi * u2)], axis=1)


def _pairs(seed: int, counters: np.ndarray) -> np.ndarray:
    return np.array([normal_pair(seed, int(c)) for c in counters])


@pytest.mark.parametrize("seed", [0, 7, 2**40 + 3])
def test_normal_pair_is_box_muller_of_the_splitmix_hash(seed: int) -> None:
    counters = np.concatenate([np.arange(4000), np.array([2**33 + 5, 2**52 - 1, 2**62 + 11])])
    got, want = _pairs(seed, counters), _reference_pairs(seed, counters)
    # the polynomials' error (~1e-15 relative) times the radius (< 7): absolute, as near zero a relative one is empty
    np.testing.assert_allclose(got, want, rtol=0.0, atol=2e-14)


def test_normal_pair_at_the_extremes_of_its_uniforms() -> None:
    """The largest radius (the high 32 bits all zero), the smallest (all one), and the angle's quarter turns, where
    the polynomials' range reduction changes branch: found by searching the reference for counters that hit them."""
    counters = np.arange(3_000_000)
    with np.errstate(over="ignore"):
        k = _mix(np.array([(7 * _GOLDEN + _GOLDEN) & _MASK], dtype=np.uint64))[0]
        z = _mix(k + counters.astype(np.uint64) * np.uint64(_GOLDEN))
    high = (z >> np.uint64(32)).astype(np.float64)
    angle = (z & np.uint64(0xFFFFFFFF)).astype(np.float64) / 2.0**30  # in quarter turns
    near_quarter = np.abs(angle - np.round(angle))
    picked = np.unique(np.concatenate([
        np.argsort(high)[:20], np.argsort(high)[-20:],  # radius ~5.5 and ~0
        np.argsort(np.abs(near_quarter - 0.5))[:20],  # the rest of the angle at +-1/8 turn
        np.argsort(near_quarter)[:20],  # exactly on a quarter turn, or next to one
    ]))
    np.testing.assert_allclose(_pairs(7, counters[picked]), _reference_pairs(7, counters[picked]), rtol=0.0,
                               atol=2e-14)


def test_normals_are_standard_normal_and_independent() -> None:
    z = standard_noise(3, 5, 4096, 40)  # (samples, steps, 2): 327,680 normals
    flat = z.reshape(-1)
    assert stats.kstest(flat, "norm").pvalue > 1e-3
    # each of the pair alone too, since Box-Muller makes them from one draw
    assert stats.kstest(z[..., 0].ravel(), "norm").pvalue > 1e-3
    assert stats.kstest(z[..., 1].ravel(), "norm").pvalue > 1e-3
    n = flat.size
    assert abs(flat.mean()) < 5.0 / np.sqrt(n)
    assert flat.var() == pytest.approx(1.0, abs=5.0 * np.sqrt(2.0 / n))
    # tails: the share beyond 3 sigma as scipy's normal gives it, within 5 standard errors
    p3 = 2.0 * stats.norm.sf(3.0)
    assert np.mean(np.abs(flat) > 3.0) == pytest.approx(p3, abs=5.0 * np.sqrt(p3 / n))
    assert abs(np.corrcoef(z[..., 0].ravel(), z[..., 1].ravel())[0, 1]) < 5.0 / np.sqrt(n / 2)
    assert abs(np.corrcoef(z[:, 1:, 0].ravel(), z[:, :-1, 0].ravel())[0, 1]) < 5.0 / np.sqrt(n / 2)
