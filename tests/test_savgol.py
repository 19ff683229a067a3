"""The planner's Savitzky-Golay matrix is scipy.signal's filter of the identity to the bit, made without importing
scipy.signal (gpmppi/mppi/savgol.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import savgol_filter

from gpmppi.mppi.config import PlannerConfig
from gpmppi.mppi.savgol import savgol_matrix


def scipys(horizon: int, window: int, order: int) -> np.ndarray:
    return savgol_filter(np.eye(horizon), window, order, axis=0, mode="nearest")


def cases() -> list[tuple[int, int, int]]:
    """(horizon, window, order): every order of every odd window up to 25 (scipy's symmetric, antisymmetric and
    general correlation paths all occur there: 5/4, 9/8, 21/20 and 23/22 are antisymmetric within DBL_EPSILON), each at
    horizons from the window itself (the held ends reach every row) to 40; wider windows at a spread of orders; the
    default window and order at every horizon to 100."""
    out = set()
    for window in range(1, 26, 2):
        for order in range(window):
            out |= {(h, window, order) for h in (window, window + 1, window + 2, 2 * window + 1, 40) if h >= window}
    for window in (27, 31, 41, 61, 99):
        out |= {(window + extra, window, order) for extra in (0, 3, 60) for order in (0, 1, 2, 3, 4, 7, 12, 26)}
    out |= {(h, 9, 2) for h in range(9, 101)}
    return sorted(out)


def test_savgol_matrix_has_scipys_bits() -> None:
    different = [c for c in cases() if savgol_matrix(*c).tobytes() != scipys(*c).tobytes()]
    assert not different, f"{len(different)} of {len(cases())} differ from scipy, e.g. {different[:5]}"


def test_savgol_matrix_of_the_shipped_settings() -> None:
    """The settings' own windows: the default (update=smooth) and the windows a short horizon is limited to."""
    for horizon in (40, 3, 8, 9, 10):
        c = PlannerConfig(horizon=horizon)
        assert c.savgol_window
        m = savgol_matrix(c.horizon, c.savgol_window, c.smoothing_order)
        assert m.flags.c_contiguous and m.shape == (horizon, horizon)
        assert m.tobytes() == scipys(c.horizon, c.savgol_window, c.smoothing_order).tobytes()


@pytest.mark.parametrize("horizon, window, order", [(10, 4, 2), (10, 5, 5), (4, 5, 2), (10, 0, 0)])
def test_savgol_matrix_refuses_what_the_settings_refuse(horizon: int, window: int, order: int) -> None:
    with pytest.raises(ValueError, match="window"):
        savgol_matrix(horizon, window, order)
