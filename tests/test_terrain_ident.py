"""The terrain-separability measures on hand-made steps: window sums, confusion, switch response, top changes, and
the separability of terrains whose predictions are apart or equal."""

from __future__ import annotations

import numpy as np

from gpmppi.terrain.separability import (
    Transitions,
    confusion,
    separability,
    switch_response,
    top_changes,
    window_sums,
)

NAMES = ["a", "b", "c"]


def test_window_sums_are_the_sums_of_consecutive_rows() -> None:
    a = np.arange(6.0)[:, None] * np.array([[1.0, 10.0]])
    np.testing.assert_allclose(window_sums(a, 3), [[3, 30], [6, 60], [9, 90], [12, 120]])


def test_confusion_counts_windows_on_one_terrain_by_the_winner() -> None:
    score = np.array([[1.0, 0.0, 0.0]] * 4 + [[0.0, 0.0, 1.0]] * 4)
    terrain = ["a"] * 4 + ["b"] * 4
    out = confusion(score, terrain, NAMES, 2)
    # three windows of two steps on a (a wins), three on b (c wins); the one straddling the change is left out
    np.testing.assert_array_equal(out, [[3, 0, 0], [0, 0, 3], [0, 0, 0]])


def _steps(rng: np.random.Generator, n: int, offset_b: float) -> Transitions:
    mean = np.zeros((n, 3, 2))
    mean[:, 1, :] = offset_b  # terrain b predicts offset_b more than a; c far off
    mean[:, 2, :] = 1.0
    var = np.full((n, 3, 2), 0.01)
    y = rng.normal(0.0, 0.1, (n, 2))  # the truth is a: mean 0, std 0.1
    return Transitions(y, mean, var, ["a"] * n)


def test_separability_sees_apart_terrains_and_not_equal_ones() -> None:
    rng = np.random.default_rng(0)
    apart = separability(_steps(rng, 400, 0.1), NAMES, (1, 20))
    p = apart["pairs"]["a|b"]
    assert p["dprime_v_median"] == 1.0 and p["llr_per_step_mean"] > 0.3 and p["true_wins_fraction"][20] > 0.95
    assert abs(apart["calibration"]["a"]["z2_v"] - 1.0) < 0.2  # the variance is the residuals' real spread
    same = separability(_steps(rng, 400, 0.0), NAMES, (20,))["pairs"]["a|b"]
    assert same["dprime_v_median"] == 0.0 and same["llr_per_step_mean"] == 0.0


def test_switch_response_is_the_time_until_the_new_terrain_passes_the_level() -> None:
    times = np.arange(11) * 0.5
    w = np.array([[1, 0, 0]] * 4 + [[0.8, 0.2, 0], [0.6, 0.4, 0], [0.4, 0.6, 0], [0, 1, 0], [0, 1, 0], [0, 1, 0]],
                 dtype=float)
    terrains = ["a"] * 4 + ["b"] * 6
    out = switch_response(times, w, terrains, NAMES)
    assert out == [{"at_s": 2.0, "from": "a", "to": "b", "seconds": 1.0}]
    assert switch_response(times, w, ["a"] * 4 + ["sand"] * 6, NAMES)[0]["seconds"] is None


def test_top_changes_count_only_after_settling() -> None:
    times = np.arange(9) * 1.0
    w = np.array([[1, 0, 0], [0, 1, 0], [1, 0, 0], [1, 0, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0], [0, 1, 0]], dtype=float)
    assert top_changes(times, w, after_s=0.0) == 4
    assert top_changes(times, w, after_s=3.0) == 2
