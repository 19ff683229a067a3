"""The novelty test's second channel: does any trained ground's velocity response, run free for a second, end where
the robot is? It sees a loss of grip, which the one-step test (gpmppi/terrain/novelty.py) cannot.

Why a second channel. On a low-grip ground (glare ice) the one-step residual under the best trained ground is as small
as on known ground while the robot drives straight or turns gently: the motors' speed loops hold the commanded wheel
speeds and the grip limit is not reached (docs/new_ground.md, "Grounds it does not flag"). Where the ground shows
itself, in a corner or a hard acceleration, the speed falls far behind the command, and those are exactly the steps
the one-step test holds off over (`NoveltyTest.transient`: starts from rest look the same, and scoring them widened
its calibrated spread 1.1-4x). A free run does not need that hold-off: every ground's response is run from the
velocity measured `horizon_steps` ago under the commands applied since, so a start or a stop is a transient the
trained grounds' responses also make, while a slide is one none of them makes, and the error it leaves piles up over
the horizon instead of being judged one step at a time.

The statistic. Per ground i, with the robot profile's velocity response (gpmppi/profile/response.py: the steady map
`S_i(u)` and the first-order rate `r_i`, fitted from the logs), a free run started at every step from the measured
(v, omega) and advanced under each step's command, `p <- p + r_i (S_i(u) - p)`; after `horizon_steps` steps its error
against the measured velocity is `e_i = (v, omega) - p_i` [m/s, rad/s]. Over the last `window_steps` errors their mean
`b_i` (2,) in units of `spread` gives `z_i = |b_i / spread|`, and the statistic is the best ground's, `z = min_i z_i`.
A run is dropped when a step does not start where the last one ended (a skipped transition) or its command lies off
the response's grid (where the map is clamped).

The calibration comes from the robot's own logs, the same held-out steps as the one-step test's (`gpmppi train`,
gpmppi.terrain.log_calibration.novelty_from_runs): `spread` is the RMS of the true ground's windowed mean error, and
`enter` the (1 - `false_rate`) quantile of the statistic over the logs' windows. A quantile of the logs, where the
one-step test has a stated level: the logs are excitation drives whose command steps the first-order response follows
worst, so the logs' tail is what known ground does at its hardest, and a task's driving stays well inside it (the
Jackal: 99.9 % quantile 7.2 spreads on its logs, at most 2.5 on its lanes and scene; glare ice's first corner 24).

Cost per step: one steady-map lookup (M grounds) and `horizon_steps` (M, 2) updates.
"""

from __future__ import annotations

import numpy as np

from gpmppi.profile.novelty_calibration import FreeRunCalibration
from gpmppi.profile.response import TerrainResponse
from gpmppi.terrain.novelty import WindowedTest

__all__ = ["DEFAULT_FREE_RUN", "FreeRunTest", "calibrate_free_run", "profile_free_run"]

# The stated default for a profile whose novelty record holds no free-run calibration (every profile trained before
# it): fitted as `gpmppi train` fits it (`novelty_from_runs`) on logs like those the shipped Jackal profile's grounds
# were made from (`gpmppi dataset -t tile -t asphalt -t grass -t sand`, seed 0; docs/new_ground.md, "The free-run
# channel"). A 1 s horizon: a slide in a corner lasts about that long, and the first-order response's error in a
# trained ground's transients (its rate is a stand-in for a higher-order plant) grows little beyond it. A 2 s window,
# as the one-step test's.
DEFAULT_FREE_RUN = FreeRunCalibration(horizon_steps=10, window_steps=20, spread=(0.0275, 0.0270), enter=7.15,
                                      width=0.95, source="default (the shipped Jackal profile's logs)")


class FreeRunTest(WindowedTest):
    """The free-run channel over M trained grounds: feed each step, read P(unknown) from this channel."""

    def __init__(self, response: TerrainResponse, calibration: FreeRunCalibration = DEFAULT_FREE_RUN) -> None:
        self.response = response
        self.calibration = calibration
        self._m = len(response.terrains)
        self._inv_spread = 1.0 / np.asarray(calibration.spread, dtype=np.float64)
        self.reset()

    def reset(self) -> None:
        # the free runs in flight: a ring of `horizon_steps` slots (K, M, 2), `_active` of them from `_head` on (the
        # oldest first); the free slots are advanced too (one vector update for all), and overwritten when a run starts
        self._runs = np.zeros((self.calibration.horizon_steps, self._m, 2))
        self._head = 0
        self._active = 0
        self._at: np.ndarray | None = None  # the measured velocity the last step ended at
        self._reset_window(self._m)  # `recorded`, when a list, keeps every completed run's error (M, 2)

    def observe(self, velocity: np.ndarray, command: np.ndarray, next_velocity: np.ndarray) -> float:
        """One step from measured (v [m/s], omega [rad/s]) `velocity` under `command` (v_ref, omega_ref) to
        `next_velocity`; P(unknown) from this channel after it."""
        v0 = np.asarray(velocity, dtype=np.float64).reshape(2)
        v1 = np.asarray(next_velocity, dtype=np.float64).reshape(2)
        u = np.asarray(command, dtype=np.float64).reshape(2)
        if not (np.all(np.isfinite(v0)) and np.all(np.isfinite(v1)) and np.all(np.isfinite(u))):
            self._active = 0
            self._at = None
            return self.probability
        covered = self.response.covers(u)
        if self._at is None or not np.array_equal(v0, self._at) or not covered:
            self._active = 0  # a skipped transition, or off the map's grid: start over from the measured velocity
        self._at = v1.copy()
        if not covered:
            return self.probability
        k = self.calibration.horizon_steps
        self._runs[(self._head + self._active) % k] = v0[None, :]
        self._active += 1
        self._runs += self.response.rate[None] * (self.response.steady_at(u)[None] - self._runs)
        if self._active < k:
            return self.probability
        error = v1[None, :] - self._runs[self._head]
        self._head = (self._head + 1) % k
        self._active -= 1
        return self._score(error)


def calibrate_free_run(
    known: list[tuple[np.ndarray, int]], horizon_steps: int = DEFAULT_FREE_RUN.horizon_steps,
    window_steps: int = DEFAULT_FREE_RUN.window_steps, false_rate: float = 1e-3, width_share: float = 0.133,
    source: str = "calibrated",
) -> FreeRunCalibration:
    """A free-run calibration from known-ground drives: `known` holds per run (free-run errors (n, M, 2) under each
    trained ground, the index of the ground the run drove on). `spread`: per channel the RMS of the true ground's
    windowed mean error; `enter`: the (1 - `false_rate`) quantile of the statistic over all windows; `width`:
    `width_share` of `enter`."""
    from gpmppi.terrain.novelty import window_statistics

    usable = [(r, i) for r, i in known if len(r) >= window_steps]
    if not usable:
        raise ValueError(f"free-run calibration: no run has a whole window of {window_steps} errors "
                         f"({horizon_steps} + {window_steps} steps); record longer drives on the trained grounds")
    true_means = [window_statistics(r, window_steps)[:, i] for r, i in usable]
    spread = np.maximum(np.sqrt(np.mean(np.concatenate(true_means) ** 2, axis=0)), 1e-6)
    stats = np.concatenate([np.min(np.linalg.norm(window_statistics(r, window_steps) / spread[None, None, :],
                                                  axis=2), axis=1) for r, _ in usable])
    level = float(np.quantile(stats, 1.0 - false_rate))
    return FreeRunCalibration(horizon_steps, window_steps, (float(spread[0]), float(spread[1])), level,
                              width_share * level, source)


def profile_free_run(model) -> FreeRunCalibration:  # noqa: ANN001 - GPModel (not imported: this module stays light)
    """The free-run channel's calibration: the robot profile's (`gpmppi train` fits it from the logs, in version 2 of
    the novelty record), else `DEFAULT_FREE_RUN`: a profile trained before the channel keeps working, with a default
    measured on the same kind of robot (its `source` says which was used)."""
    stored = getattr(getattr(model, "novelty", None), "free_run", None)
    return stored if isinstance(stored, FreeRunCalibration) else DEFAULT_FREE_RUN
