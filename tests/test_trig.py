"""`gpmppi.trig`: the kernels' cos and sin against numpy's, over the angles a planner meets and beyond (to 2e-15)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpmppi.trig import cos_sin, quarter_turned


def _both(xs: np.ndarray) -> np.ndarray:
    return np.array([cos_sin(float(x)) for x in xs])


def test_cos_sin_matches_numpy_over_headings_of_many_turns() -> None:
    rng = np.random.default_rng(0)
    xs = np.concatenate([
        rng.uniform(-4.0 * np.pi, 4.0 * np.pi, 20_000),  # a heading, wrapped or not
        rng.uniform(-1e4, 1e4, 5_000),  # unwrapped after ~1,600 turns
        rng.uniform(-1e5, 1e5, 2_000),
        np.arange(-64, 65) * (np.pi / 4),  # every octant's edge: where the quarter turn taken out changes
        np.nextafter(np.arange(-64, 65) * (np.pi / 4), np.inf),
        [0.0, -0.0, 1e-300, -1e-300, 5e-324],
    ])
    got = _both(xs)
    # numpy's own reduction of a large angle is exact; ours loses ~1e-16 per 1e3 of |x|, the polynomials ~1e-15
    tol = 2e-15 * np.maximum(1.0, np.abs(xs) / 1e3)
    for i, ref in enumerate((np.cos(xs), np.sin(xs))):
        err = np.abs(got[:, i] - ref)
        assert np.all(err <= tol), (i, float(err.max()), float(xs[np.argmax(err / tol)]))
    # small angles: sin x = x to the last bits (no absolute floor hides a relative error there)
    small = np.array([1e-300, 1e-20, 1e-8, -3e-6])
    np.testing.assert_allclose(_both(small)[:, 1], np.sin(small), rtol=1e-15)


def test_quarter_turned_turns_by_any_number_of_quarters() -> None:
    for q in range(-9, 10):
        for a in (-0.78, -0.1, 0.0, 0.3, 0.78):
            c, s = math.cos(a), math.sin(a)
            want = [(c, s), (-s, c), (-c, -s), (s, -c)][q % 4]  # turned exactly, by swaps and signs
            assert quarter_turned(a, float(q)) == (pytest.approx(want[0], abs=2e-15), pytest.approx(want[1], abs=2e-15))


def test_non_finite_angles_give_nan() -> None:
    for x in (math.inf, -math.inf, math.nan):
        c, s = cos_sin(x)
        assert math.isnan(c) and math.isnan(s)
