"""The no-kill reference of `gpmppi bench startup`: the lane RMSE ratio of consecutive windows, away from kills."""

from __future__ import annotations

import numpy as np

from tools.lane_windows import consecutive_window_ratios, ratio_summary

NS = 1_000_000_000
R = 8.0
CENTRE = np.stack([R * np.cos(np.linspace(0, 2 * np.pi, 720, endpoint=False)),
                   R * np.sin(np.linspace(0, 2 * np.pi, 720, endpoint=False))], axis=1)


def _drive(offsets_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """States at 10 Hz around the circle, each `offset` outside the centre line."""
    a = np.linspace(0.0, 3.0, offsets_m.size)
    xy = np.stack([(R + offsets_m) * np.cos(a), (R + offsets_m) * np.sin(a)], axis=1)
    return np.arange(offsets_m.size) * NS // 10, xy


def test_ratios_of_consecutive_windows_and_the_kills_left_out() -> None:
    # 30 s: 10 mm off the line for 15 s, then 20 mm (its RMSE doubles there), with alternating signs
    sign = np.where(np.arange(300) % 2 == 0, 1.0, -1.0)
    offsets = np.where(np.arange(300) < 150, 0.010, 0.020) * sign
    stamps, xy = _drive(offsets)
    ratios = consecutive_window_ratios(stamps, xy, CENTRE, True, window_s=5.0, step_s=1.0)
    # boundaries every second from 5 s to 24 s (the last state is at 29.9 s): 20; the one at 15 s has 10 mm before
    # and 20 mm after, the one at 12 s 3 s of 10 mm and 2 s of 20 mm after
    assert ratios.size == 20
    np.testing.assert_allclose(ratios[15 - 5], 2.0, rtol=0.02)
    np.testing.assert_allclose(ratios[12 - 5], np.sqrt((3 * 1e-4 + 2 * 4e-4) / 5) / 0.010, rtol=0.02)
    assert np.sum(ratios > 1.05) == 9  # 11-19 s: one window holds some of the 20 mm stretch, the other less
    np.testing.assert_allclose(np.median(ratios), 1.0, atol=0.02)
    # a kill at 15 s (and 5 s each side): no boundary whose windows touch [10 s, 20 s], 5 s the only one left
    kept = consecutive_window_ratios(stamps, xy, CENTRE, True, excluded=[(10 * NS, 20 * NS)], window_s=5.0)
    assert kept.size == 1 and np.allclose(kept, 1.0, atol=0.02)
    summary = ratio_summary(ratios)
    assert summary["n"] == 20 and summary["share_over_limit"] == round(float(np.mean(ratios > 1.5)), 3) > 0
    assert ratio_summary(np.zeros(0))["n"] == 0
