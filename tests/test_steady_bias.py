"""The GP's one-step error in steady straight driving near the top speed (gpmppi/terrain/steady_bias.py), and the
excitation's added top holds (`Excitation(top_holds=...)`, `gpmppi dataset --top-holds`)."""

from __future__ import annotations

import numpy as np
import pytest

from gpmppi.plant.excitation import TOP_HOLD_S, TOP_HOLD_SHARES, Excitation


def test_top_holds_are_off_by_default_and_added_between_the_plain_segments() -> None:
    plain, off = Excitation(seed=7), Excitation(seed=7, top_holds=0.0)
    for _ in range(30):
        np.testing.assert_array_equal(plain.next_segment(), off.next_segment())
        assert not off.extra
    reference = Excitation(seed=7)
    exc = Excitation(seed=7, top_holds=0.3, top_speed=1.6)
    tops = 0
    for _ in range(200):
        seg = exc.next_segment()
        if exc.extra:  # a straight hold at 0.7-1.0 x the top speed, 5-8 s
            tops += 1
            assert np.all(seg == seg[0]) and seg[0, 1] == 0.0
            assert TOP_HOLD_SHARES[0] * 1.6 <= seg[0, 0] <= TOP_HOLD_SHARES[1] * 1.6
            assert TOP_HOLD_S[0] / 0.1 - 1e-9 <= len(seg) <= TOP_HOLD_S[1] / 0.1 + 1e-9
        else:  # the plain stream, segment for segment, the top holds left out
            np.testing.assert_array_equal(seg, reference.next_segment())
    assert 30 <= tops <= 60  # after about 0.3 of the plain segments, never two in a row
    with pytest.raises(ValueError, match="top_holds"):
        Excitation(top_holds=1.5)


@pytest.mark.slow
def test_the_drive_counts_the_plain_segments_distance_and_adds_the_top_holds() -> None:
    from gpmppi.plant.excitation import simulate_dataset
    from gpmppi.plant.terrains import load_terrains

    terrains = load_terrains()
    plain = simulate_dataset(terrains, ["asphalt"], distance=150.0, seed=2, noise=False)["asphalt"]
    top = simulate_dataset(terrains, ["asphalt"], distance=150.0, seed=2, noise=False, top_holds=0.5)["asphalt"]
    assert top.distance > plain.distance + 20.0  # the holds' metres on top
    # the straight holds near the top speed settle: steady rows at 1.4-2.0 m/s, which the plain drive hardly has
    def settled_straight(run) -> int:  # noqa: ANN001
        v, cmd = run.true_state[:, 3], run.command
        return int(np.sum((cmd[:, 0] >= 1.4) & (cmd[:, 1] == 0.0) & (np.abs(v - cmd[:, 0]) < 0.03)))

    assert settled_straight(top) >= 50 + 3 * settled_straight(plain)
