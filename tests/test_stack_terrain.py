"""tools.stack_terrain's scores of a launch's recorded weights: the novelty test's false alarms."""

from __future__ import annotations

import pytest

from tools.stack_terrain import novelty_scores


def test_the_false_alarm_share_counts_the_time_on_trained_ground_with_p_unknown_above_a_half() -> None:
    stamps = [k * 100_000_000 for k in range(100)]  # 10 s of states at 10 Hz
    # P(unknown) above 0.5 on 5 states, the latch (the planner's caution) held for 10; no weights for the last 20
    unknown = [(s, 0.8 if 40 <= k < 45 else 0.1, 40 <= k < 50) for k, s in enumerate(stamps[:80])]
    truth = ["mulch"] * 100
    scores = novelty_scores(stamps, unknown, truth, ["gravel", "mulch", "wet_concrete"])
    assert scores["unknown_share"] == pytest.approx(5 / 80)
    assert scores["unknown_active_share"] == pytest.approx(10 / 80)
    # time on a ground the profile lacks is no false alarm: none of the time is counted
    assert novelty_scores(stamps, unknown, ["sand"] * 100, ["gravel", "mulch"])["unknown_share"] is None
    assert novelty_scores(stamps, [], truth, ["mulch"]) == {"unknown_share": None, "unknown_active_share": None}
