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

The hold: "known again" only from runs that could have shown a slide. Glare ice shows itself only where the commands
ask for more grip than it has (a corner); on a straight at steady speed its free run is a trained ground's, so a plain
window of the straight's errors carries no evidence either way, and the alarm raised at a corner fell on the next
straight (on the square lane the caution was on for ~15 % of the run, and learning, which waits 3 s of P(unknown)
> 0.5, rarely started). So beside the plain window the channel keeps the last `window_steps` *informative* errors,
those of runs whose commands asked, at one step at least, for a sideways acceleration `|v_ref omega_ref|` of
`informative_demand` (1.2 m/s^2) or more, however long ago they were. The plain window raises the alarm as before;
while it is above the level the informative window starts again (what comes after the alarm decides), and the
statistic holds the alarm's peak until a whole informative window has been driven since; from then on it is the
larger of the two windows'. So the alarm falls only once a window of informative runs driven after it is explained
by a trained ground (a corner on known ground). Starting again matters: a corner's runs after its slide leave small
errors, of the opposite sign on the light robot, and a window that mixed them with the slide's fell below the level
within the corner there. Why sideways demand, and 1.2: in GP-MPPI's closed
loops on the Jackal's lanes (docs/new_ground.md, "The hold across straights") the glare-ice runs with an error above
15 spreads asked for 1.04-3.10 m/s^2 at their largest (34 of 39 for 1.2 or more), while the circle's gentle turn
asked for at most 0.8 and the straights' steering corrections mostly under 0.4, and neither showed it; speed changes
(up to 2.4 m/s^2 on the circle) never showed a slide. 1.2 m/s^2 is glare ice's lateral grip (mu_lat 0.12 x g): a
run that asks for less cannot show that ground, and it is above the circle's 0.8, whose runs cannot show it either.
From 0.8 to 2.0 the alarm held on the glare-ice runs replayed (the Jackal's and the light robot's); above 1.2 the
trained corners' informative windows reach a little higher (2.7-2.9 spreads against 2.25).

Cost per step: one steady-map lookup (M grounds) and `horizon_steps` (M, 2) updates.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from gpmppi.profile.novelty_calibration import FreeRunCalibration
from gpmppi.profile.response import TerrainResponse
from gpmppi.terrain.novelty import WindowedTest

__all__ = ["DEFAULT_FREE_RUN", "INFORMATIVE_DEMAND", "FreeRunTest", "calibrate_free_run", "profile_free_run"]

# The stated default for a profile whose novelty record holds no free-run calibration (every profile trained before
# it): fitted as `gpmppi train` fits it (`novelty_from_runs`) on logs like those the shipped Jackal profile's grounds
# were made from (`gpmppi dataset -t tile -t asphalt -t grass -t sand`, seed 0; docs/new_ground.md, "The free-run
# channel"). A 1 s horizon: a slide in a corner lasts about that long, and the first-order response's error in a
# trained ground's transients (its rate is a stand-in for a higher-order plant) grows little beyond it. A 2 s window,
# as the one-step test's.
DEFAULT_FREE_RUN = FreeRunCalibration(horizon_steps=10, window_steps=20, spread=(0.0275, 0.0270), enter=7.15,
                                      width=0.95, source="default (the shipped Jackal profile's logs)")


# The sideways acceleration [m/s^2] a free run's commands must ask for (|v_ref omega_ref| at one step at least) for its
# error to count towards "known again" (the hold, above): glare ice's lateral grip, above what the Jackal's circle
# (at most 0.8) and straights (mostly under 0.4) ask for, below its square's corners (2-3)
INFORMATIVE_DEMAND = 1.2


class FreeRunTest(WindowedTest):
    """The free-run channel over M trained grounds: feed each step, read P(unknown) from this channel.

    `statistic` is the larger of the plain window's (`window_statistic`) and the window of the last informative runs'
    (`informative_statistic`, once it holds `window_steps` of them), and after an alarm the alarm's peak until such a
    window has been driven since; `informative_demand` 0: the plain window alone (no hold)."""

    def __init__(self, response: TerrainResponse, calibration: FreeRunCalibration = DEFAULT_FREE_RUN,
                 informative_demand: float = INFORMATIVE_DEMAND) -> None:
        self.response = response
        self.calibration = calibration
        self.informative_demand = informative_demand  # [m/s^2]
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
        # per ring slot: the largest sideways acceleration |v_ref omega_ref| [m/s^2] its run's commands asked for
        self._demand = np.zeros(self.calibration.horizon_steps)
        self._reset_window(self._m)  # `recorded`, when a list, keeps every completed run's error (M, 2)
        # the last `window_steps` errors of informative runs (however old) and their sum
        self._informative: deque[np.ndarray] = deque()
        self._informative_sum = np.zeros((self._m, 2))
        self.window_statistic = 0.0  # the plain window's statistic
        self.informative_statistic = 0.0  # the informative runs' window's (0 until it is whole)
        self._held = 0.0  # the last alarm's peak statistic, held until an informative window was driven since
        # the demands of the plain window's runs (an alarm is held only where one of them asked for grip)
        self._window_demand: deque[float] = deque(maxlen=self.calibration.window_steps)

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
        slot = (self._head + self._active) % k
        self._runs[slot] = v0[None, :]
        self._demand[slot] = 0.0
        self._active += 1
        self._runs += self.response.rate[None] * (self.response.steady_at(u)[None] - self._runs)
        np.maximum(self._demand, abs(u[0] * u[1]), out=self._demand)
        if self._active < k:
            return self.probability
        error = v1[None, :] - self._runs[self._head]
        demand = float(self._demand[self._head])
        self._head = (self._head + 1) % k
        self._active -= 1
        self._score(error)
        return self._hold(error, demand) if self.informative_demand > 0 else self.probability

    def _hold(self, error: np.ndarray, demand: float) -> float:
        """Keep `error` (M, 2) in the informative runs' window if its run asked for `demand` [m/s^2] >=
        `informative_demand`; the statistic is the larger of the plain window's and the informative one's, or, after
        an alarm until a whole informative window has been driven since, the alarm's peak. P(unknown) after it."""
        self.window_statistic = self.statistic
        self._window_demand.append(demand)
        if self.statistic >= self.calibration.enter:
            # the plain window says unknown. Where its commands asked for grip, "known again" must come from runs
            # driven after it (a corner's runs after its slide mix its errors with small ones of opposite sign, and
            # the light robot's mean of them fell below the level within its corner), so the informative window
            # starts again, and the peak holds. An alarm of runs that asked for no grip (the stack's start: a 0.6 s
            # planner stall, the watchdog's zero at 1.07 m/s, the robot braking harder than the response's first
            # order) is not held: on a circle, which never asks for 1.2 m/s^2, it held for the whole run
            if max(self._window_demand) >= self.informative_demand:
                self._held = max(self._held, self.statistic)
                self._informative.clear()
                self._informative_sum[:] = 0.0
                self.informative_statistic = 0.0
            return self.probability
        if demand >= self.informative_demand:
            self._informative.append(error)
            self._informative_sum += error
            if len(self._informative) > self.calibration.window_steps:
                self._informative_sum -= self._informative.popleft()
        if len(self._informative) >= self.calibration.window_steps:
            z = np.linalg.norm(self._informative_sum / len(self._informative) * self._inv_spread[None, :], axis=1)
            self.informative_statistic = float(z.min())
            self._held = 0.0  # a whole window of informative runs since the alarm: it decides from now on
        self.statistic = max(self.statistic, self.informative_statistic, self._held)
        return self.probability


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
