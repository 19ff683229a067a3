"""An absolute test of fit: is the ground under the robot one of the trained grounds at all?

The terrain filter (gpmppi.terrain.estimator) scores the trained grounds against each other, so on a ground none of
them explains it still puts its weight somewhere (sand reads as grass). This module says how well the best of them
explains the recent steps, compared with how well the right ground explains steps of known ground.

The statistic. Per step and trained ground i the filter has the residual it did not explain, `e_i = y - pred_i`
(the measured one-step velocity residual minus ground i's GP mean and its command-change part; v [m/s], omega
[rad/s]). Over the last `window_steps` scored steps their mean `b_i` (2,) is taken; in units of `spread` (the
spread of that windowed mean on known ground) its length is `z_i = |b_i / spread|`. The statistic is the best
ground's, `z = min_i z_i`: a new ground is one that *no* trained ground explains. A windowed mean and not a mean
square: a new ground shifts the residual (sand's drag takes ~0.03 m/s off every 0.1 s step, where the right ground's
windowed mean stays within ~0.006), while the step-to-step scatter, which a mean square would add, is as large on
known ground under sharp manoeuvres as on new ground.

The probability. `P(unknown) = 1 / (1 + exp(-(z - enter) / width))`: 0.5 at `enter`, the level that known ground
exceeds only rarely (calibrated on held-out known-ground steps: `calibrate`), rising over `width`. Transients (a
step from rest, a v command more than `EstimatorConfig.gp_max_speed_gap` from the speed either way) and the second
after them are not scored (`NoveltyTest.transient`): the window keeps the steps before them.

The decision. `UnknownLatch` turns the probability into the published `unknown_active` with hysteresis: set when
the probability exceeds `enter_p`, cleared only after it stays below `exit_p` for `exit_steps` steps, so a window that
straddles a manoeuvre neither clears nor sets it on one step.

Pure and cheap: per step one (M, 2) sum update and M norms.

A second channel, the free run of each ground's velocity response (gpmppi/terrain/free_run.py), sees what this test
holds off over or cannot see (a slide: grip lost); the estimator publishes the larger of the two probabilities.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from gpmppi.profile.novelty_calibration import NoveltyCalibration

__all__ = ["DEFAULT_CALIBRATION", "ENTER_SPREADS", "NoveltyTest", "UnknownLatch", "WindowedTest", "calibrate",
           "profile_novelty", "window_statistics"]


# where P(unknown) = 0.5, in spreads of the windowed mean residual: above every window of driving a task on a trained
# ground measured (closed loops on the lanes and the obstacle scene, three robots: docs/new_ground.md), below sand's
# and mud's
ENTER_SPREADS = 3.5
# The window: 2 s. The residual a trained ground leaves on known ground is partly scatter, which a longer mean shrinks
# (its spread falls from 0.0052 to 0.0041 m/s and 0.0147 to 0.0119 rad/s from 10 to 20 steps on the Jackal's logs),
# while a new ground's shift stays: sand's median is 5.1 spreads of a 1 s window and 6.4 of a 2 s one, the highest
# trained-ground window of the closed loops falls from 3.4 to 2.3, so grounds from ~55 % of sand's shift on are
# flagged (1 s: ~70 %), and sand still within ~1 s of the change (docs/new_ground.md). A 3 s window would gain little
# more (known max 1.9) and leave a ground near the level no time within the 3 s allowed.
# The transients the test holds off over (`NoveltyTest.transient`): a step from rest (below both) or with the v command
# more than `max_speed_gap` from the speed (either way), and the `SETTLE_STEPS` after the last such step. At a start
# from rest the plant's hidden states (the motors' currents and integrators) are far from where the training drives had
# them, and in the stack the base's first output of a start is paired with the step only to within a base tick;
# egress's watchdog stops the robot with a step to 0. A start from rest in `gpmppi launch` scored residuals of 15
# spreads on its first step and held P(unknown) at 1 on asphalt (docs/new_ground.md, "A start from rest"); 1 s covers
# the start's ramp there. Scoring the steps far below the command while moving (a slide on glare ice) was tried: the
# excitation logs' command steps then widen the calibrated spread 1.1-4x (the light robot's 4x) and blind the test.
REST_SPEED = 0.05  # [m/s]
REST_TURN_RATE = 0.1  # [rad/s]
SETTLE_STEPS = 10
# The stated default for a profile that holds no novelty calibration: the spread fitted on logs like those the shipped
# Jackal profile's grounds were made from (`gpmppi dataset` seed 0, `gpmppi train`'s `novelty_from_runs` with the
# filter's gating before the hold-off; with it, 0.0036 / 0.0115 on the same logs; docs/new_ground.md, "Calibration"),
# with `ENTER_SPREADS`. The page's Jackal numbers are measured with this default.
DEFAULT_CALIBRATION = NoveltyCalibration(window_steps=20, spread=(0.0041, 0.0119), enter=ENTER_SPREADS, width=0.45,
                                         source="default (the shipped Jackal profile's logs)")


class WindowedTest:
    """What both channels of the novelty test share (this module's `NoveltyTest`, gpmppi.terrain.free_run's
    `FreeRunTest`): each step's per-ground errors (M, 2) [m/s, rad/s] go into a window of the last `window_steps`;
    their mean in units of the calibration's `spread`, the best ground's length, is the statistic; its calibration
    turns it into P(unknown). A subclass sets `calibration` and `_inv_spread`, calls `_reset_window(M)` from its
    `reset` and `_score(error)` once it has a step's errors."""

    calibration: NoveltyCalibration  # or FreeRunCalibration: both have `window_steps` and `probability(z)`
    _inv_spread: np.ndarray

    def _reset_window(self, n_terrains: int) -> None:
        # with `recorded` a list, every scored step's errors (M, 2) are kept there too (calibration from logs)
        self.recorded: list[np.ndarray] | None = getattr(self, "recorded", None)
        self._window: deque[np.ndarray] = deque()
        self._sum = np.zeros((n_terrains, 2))
        self.statistic = 0.0
        self.best = -1  # the ground that explains the window best (-1: none scored yet)

    def _score(self, error: np.ndarray) -> float:
        """Add one step's errors (M, 2), an array no one changes after; P(unknown) after it."""
        self._window.append(error)
        if self.recorded is not None:
            self.recorded.append(error)
        self._sum += error
        if len(self._window) > self.calibration.window_steps:
            self._sum -= self._window.popleft()
        z = np.linalg.norm(self._sum / len(self._window) * self._inv_spread[None, :], axis=1)
        self.best = int(np.argmin(z))
        self.statistic = float(z[self.best])
        return self.probability

    @property
    def ready(self) -> bool:
        """Whether a whole window has been scored (before: P(unknown) reads 0)."""
        return len(self._window) >= self.calibration.window_steps

    @property
    def probability(self) -> float:
        return self.calibration.probability(self.statistic) if self.ready else 0.0


class NoveltyTest(WindowedTest):
    """The windowed test of fit over M trained grounds: feed each step's per-ground residuals, read P(unknown)."""

    def __init__(self, n_terrains: int, calibration: NoveltyCalibration = DEFAULT_CALIBRATION,
                 max_speed_gap: float = 0.3) -> None:
        self.calibration = calibration
        self.max_speed_gap = max_speed_gap  # [m/s] a step whose v command and measured v differ more is a transient
        self._m = n_terrains
        self._inv_spread = 1.0 / np.asarray(calibration.spread, dtype=np.float64)
        self.reset()

    def reset(self) -> None:
        self._reset_window(self._m)
        self._settle = 0  # steps still to pass unscored after the last transient step

    def transient(self, v_command: float, v: float, omega: float) -> bool:
        """Whether a step from measured (v [m/s], omega [rad/s]) under the v command [m/s] is a transient the test
        does not score: the robot at rest, or the command more than `max_speed_gap` from the speed either way (a
        start, a stop the watchdog commands; the filter's GP evidence leaves out the first kind too)."""
        at_rest = abs(v) < REST_SPEED and abs(omega) < REST_TURN_RATE
        return at_rest or abs(v_command - v) > self.max_speed_gap

    def observe(self, residuals: np.ndarray, transient: bool = False) -> float:
        """Add one step's residuals (M, 2) under each ground; P(unknown) after it. A `transient` step, and the
        `SETTLE_STEPS` after the last one, are not scored (the window keeps the steps before them)."""
        if transient:
            self._settle = SETTLE_STEPS
            return self.probability
        if self._settle > 0:
            self._settle -= 1
            return self.probability
        r = np.asarray(residuals, dtype=np.float64).reshape(self._m, 2)
        if not np.all(np.isfinite(r)):
            return self.probability
        return self._score(r.copy())


@dataclass
class UnknownLatch:
    """`unknown_active` with hysteresis: on above `enter_p`; off after `exit_steps` steps in a row below `exit_p`."""

    enter_p: float = 0.5
    exit_p: float = 0.2
    exit_steps: int = 10
    active: bool = False
    _below: int = 0

    def update(self, p: float) -> bool:
        """The decision after one step's probability `p`."""
        if p > self.enter_p:
            self.active, self._below = True, 0
        elif self.active:
            self._below = self._below + 1 if p < self.exit_p else 0
            if self._below >= self.exit_steps:
                self.active, self._below = False, 0
        return self.active


def window_statistics(residuals: np.ndarray, window_steps: int) -> np.ndarray:
    """(n - W + 1, M, 2) the mean residual of every window of `window_steps` consecutive steps of `residuals`
    (n, M, 2): what `NoveltyTest` reads, for every full window of a recording."""
    r = np.asarray(residuals, dtype=np.float64)
    c = np.cumsum(np.concatenate([np.zeros((1,) + r.shape[1:]), r]), axis=0)
    return (c[window_steps:] - c[:-window_steps]) / window_steps


def calibrate(
    known: list[tuple[np.ndarray, int]], window_steps: int = DEFAULT_CALIBRATION.window_steps,
    enter: float | None = ENTER_SPREADS, false_rate: float = 1e-3, width_share: float = 0.133,
    source: str = "calibrated",
) -> NoveltyCalibration:
    """A calibration from held-out steps of known ground: `known` holds per run (residuals (n, M, 2) under each
    trained ground, the index of the ground the run drove on).

    `spread`: per channel the RMS of the true ground's windowed mean residual. `enter`: given (the default,
    `ENTER_SPREADS`), or None: the (1 - `false_rate`) quantile of the statistic (best ground's length in units of
    `spread`) over all windows, so that known ground reaches P = 0.5 in about that share of them. Given by default
    because training logs are excitation drives, whose sharp command changes give the statistic heavier tails than
    driving a task does (the shipped Jackal's, 2 s window: 99.9 % quantile 4.5 on the logs, at most 2.3 on its lanes
    and scene; docs/new_ground.md). `width`: `width_share` of `enter`.
    """
    true_means = [window_statistics(r, window_steps)[:, i] for r, i in known if len(r) >= window_steps]
    if not true_means:
        raise ValueError(f"novelty calibration: no run has a whole window of {window_steps} steps; record longer "
                         "drives on the trained grounds")
    spread = np.sqrt(np.mean(np.concatenate(true_means) ** 2, axis=0))
    spread = np.maximum(spread, 1e-6)
    stats = np.concatenate([
        np.min(np.linalg.norm(window_statistics(r, window_steps) / spread[None, None, :], axis=2), axis=1)
        for r, _ in known if len(r) >= window_steps])
    level = float(np.quantile(stats, 1.0 - false_rate)) if enter is None else float(enter)
    return NoveltyCalibration(window_steps, (float(spread[0]), float(spread[1])), level, width_share * level, source)


def profile_novelty(model) -> NoveltyCalibration:  # noqa: ANN001 - GPModel (not imported: this module stays light)
    """The novelty calibration the estimator runs with: the robot profile's (`gpmppi train` fits it from the logs'
    held-out steps), else `DEFAULT_CALIBRATION`. The default and not a refusal: a profile made before this test
    (every v2 profile so far, the paper's converted models) must keep working, and the default was measured on the
    same kind of robot; its `source` says which one was used, and the terrain service logs it."""
    stored = getattr(model, "novelty", None)
    return stored if isinstance(stored, NoveltyCalibration) else DEFAULT_CALIBRATION
