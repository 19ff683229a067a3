"""Online terrain-weight estimators: which of the trained terrains explains the recent motion.

`BayesTerrainEstimator` (the default) filters over the terrains with each one's GP prediction, the command-change
response and the steady response map fitted from the robot's logs; `make_estimator` builds the one a configuration
names (the paper's least squares, `TerrainEstimator`, lives in `gpmppi.terrain.least_squares`).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from gpmppi.gp.exact import ExactPredictor
from gpmppi.gp.model_file import GPModel
from gpmppi.models.dynamic_unicycle import velocity_step_exact
from gpmppi.terrain.estimate import EstimatorLike, TerrainEstimate
from gpmppi.terrain.free_run import FreeRunTest, profile_free_run
from gpmppi.terrain.least_squares import TerrainEstimator, checked_vector
from gpmppi.terrain.novelty import NoveltyTest, UnknownLatch, profile_novelty
from gpmppi.terrain.settings import EstimatorConfig, profile_calibration

# command changes the roughness has seen before the response is scored: a few, so that commands jittery from the
# start are not scored on a chance small first change, and no more, so that the evidence starts early
ROUGHNESS_WARMUP_STEPS = 3

__all__ = ["BayesTerrainEstimator", "make_estimator"]


class BayesTerrainEstimator:
    """A recursive Bayesian filter over which trained terrain is under the robot, using the GP's variances.

    Each step's measured velocity residual `y` is scored under every terrain i by its exact GP prediction:
    `l_i = log N(y; m_i + g_i du, s_i^2)` (v and omega together), divided by `temperature`, where

    - `g_i du`: the part of the residual that follows the change of command `du` since the previous step. The GP's
      inputs do not carry the previous command, yet the motor drivers' setpoint lag makes the next velocity depend
      on it, and MPPI's commands change every tick: on closed-loop steps this part is most of the residual (its
      correlation with `du` is -0.8 to -0.9 on tile and grass), and it differs by terrain (wheels spin up on tile).
      `command_change: per_terrain` takes `g_i` from per-terrain gains fitted offline on each training terrain's
      excitation drives (the robot profile's calibration, fitted from its logs by `gpmppi train`, or explicit
      `command_gains`); `online` fits one gain shared by all terrains as it goes; `none` drops the term;
    - `s_i^2` = the GP's latent variance + its likelihood noise + an extra spread shared by all terrains: the GP's
      noise was fitted on training drives and is 2-4x too small for closed-loop steps (measurement noise on both ends
      of a step), and a likelihood that overconfident throws the posterior about on every step. The extra spread is
      fitted online on the residual of the weighted prediction (exponential forgetting over `calibration_steps`,
      starting from `extra_noise_std`); it does not depend on which terrain is true. With `variance: shared` (the
      default) every terrain is scored against the weighted mean of the spreads, so the terrains are told apart by
      what they predict, not by their training noise.

    To `l_i` is added the log-likelihood of the terrain's response (`response: steady_map`,
    gpmppi/profile/response.py): each terrain's measured steady-state velocity under the commands, run free through
    a first-order rate from the measured velocity, its residual averaged over `response_smoothing_steps` and scored
    against `response_spread`. The GP's inputs lack the plant's hidden states, so at a held command its one-step
    mean is off by as much as the terrains differ, and smooth commands drive close to steady state; the steady map
    is right there by construction. Scored only while the commands are smooth (`response_max_roughness`): under
    jittery ones its average is biased, and the command-change term carries the evidence instead.

    With `gp_anchor` each terrain's GP mean is first shifted by its bias at that terrain's measured steady state under
    the command (`_steady_bias`): the GP, fitted on transient-rich drives with 300 shared inputs, is off at steady
    driving by about as much as the terrains differ (on the Jackal's lanes it read steady asphalt as tile for seconds
    after every start), while the steady map is right there by construction.

    Neither model holds during a start from rest: the plant's PI integrators and torque limit are far from where the
    training drives had them, so the first second reads as asphalt on every terrain (the response's first-order rate
    and the GP's command-change gains both lag or lead the torque-limited ramp differently per terrain). A step whose
    v command exceeds the measured speed by more than `gp_max_speed_gap` adds no GP evidence, and a response channel
    whose measured velocity lies further than `response_max_transient` from any terrain's steady state is not scored
    (its free run restarts from the measured velocity), so the evidence starts once the robot is up to speed.

    The weights are the posterior of a hidden terrain that changes with probability `switch_prob` per step (a
    hidden Markov model's forward filter), published with hysteresis on which terrain leads (`_published`):

        prior_i = (1 - switch_prob) w_i + switch_prob / M,     w_i <- prior_i exp(l_i) / sum_j prior_j exp(l_j)

    Why this and not the least-squares mixture: the terrains' mean residuals are close and collinear on the states a
    controller visits, so a least-squares fit over a short window throws its weight from one vertex of the simplex
    to another on noise, and a fit without the predictive variances mistakes the noisier terrain's data for another
    terrain's; the filter weighs each step by how far apart the predictions are against their spread, accumulates
    evidence for as long as the ground stays, and `switch_prob` bounds how sure it gets, so how long a change of
    terrain takes to show (about log(M / switch_prob) nats of evidence).
    """

    def __init__(self, model: GPModel, config: EstimatorConfig) -> None:
        self.model = model
        self.config = config
        self.history = config.history
        self.min_history = config.min_history
        self._m = len(model.terrains)
        self._predictor = ExactPredictor(model)
        self._noise = np.asarray(model.noise, dtype=np.float64).reshape(self._m, 2)
        self._rows: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=config.history)  # (y (2,), predictions (M, 2))
        # the robot profile's calibration, unless the settings name explicit gains or a response file
        self._terrain_gains, self._response = profile_calibration(config, model)
        # the steady map the GP's means are anchored to (gp_anchor): the response's, also when it is not scored
        self._anchor_map = None
        if config.gp_anchor:
            self._anchor_map = (self._response if self._response is not None else
                                profile_calibration(config.model_copy(update={"response": "steady_map"}), model)[1])
        self._response_spread = np.asarray(config.response_spread, dtype=np.float64)
        self._max_roughness = np.asarray(config.response_max_roughness, dtype=np.float64)
        self._max_transient = np.asarray(config.response_max_transient, dtype=np.float64)
        # the absolute test of fit ("none of these grounds"): the profile's calibration or the stated default
        self.novelty = (NoveltyTest(self._m, profile_novelty(model), config.gp_max_speed_gap) if config.novelty
                        else None)
        # its second channel, the free run of each ground's velocity response (needs the response map)
        self.free_run: FreeRunTest | None = None
        if config.novelty and config.novelty_free_run:
            free_map = self._response if self._response is not None else self._anchor_map
            if free_map is None and (model.calibration is not None or config.response_file is not None):
                free_map = profile_calibration(config.model_copy(update={"response": "steady_map"}), model)[1]
            if free_map is not None:
                self.free_run = FreeRunTest(free_map, profile_free_run(model), config.novelty_grip_demand)
        self.reset()

    def reset(self, weights: np.ndarray | None = None) -> None:
        """Forget the evidence and the online calibration; start from `weights` (default uniform)."""
        self._rows.clear()
        self._seen = 0
        w = np.full(self._m, 1.0 / self._m) if weights is None else checked_vector("weights", weights, self._m)
        if np.any(w < 0) or abs(w.sum() - 1.0) > 1e-6:
            raise ValueError(f"weights must lie on the simplex, got {w.tolist()}")
        self._weights = w / w.sum()
        self._posterior = self._weights.copy()
        self._leader: int | None = None  # the terrain on top of the last published weights (None: none published)
        self._established = False  # whether the evidence has put the leader `hysteresis_odds` ahead of all others
        self._u_prev: np.ndarray | None = None
        self._since_start = 0  # steps since the last one the start gate held (response_settle_steps)
        # exponentially forgotten sums of the calibration: du^2, du * e, and the spread beyond the GP's
        self._s_dd = np.zeros(2)
        self._s_de = np.zeros(2)
        self._extra_var = np.square(np.asarray(self.config.extra_noise_std, dtype=np.float64))
        self._sum_spread = np.zeros(2)
        self._calibrated = 0.0  # effective number of steps in the calibration sums
        # the response evidence: each terrain's free-run velocity (M, 2), the measured state it has reached (the last
        # observed next state: a step that does not start there re-anchors), and the averaged residual (M, 2)
        self._response_pred: np.ndarray | None = None
        self._response_at: np.ndarray | None = None
        self._response_residual = np.zeros((self._m, 2))
        # mean |du|/dt over the last ~10 steps [m/s^2, rad/s^2] (an exponential average, divided by its weight so far
        # so that the first changes count fully), and how many changes it has seen
        self._roughness_sum = np.zeros(2)
        self._roughness_weight = 0.0
        self._roughness_seen = 0
        self._unknown = 0.0
        self._channel = ""  # the channel that gave `_unknown` ("one-step", "free-run"; "": neither has a window yet)
        self._latch = UnknownLatch()
        if self.novelty is not None:
            self.novelty.reset()
        if self.free_run is not None:
            self.free_run.reset()

    @property
    def weights(self) -> np.ndarray:
        return self._weights.copy()

    def hold_unknown(self) -> None:
        """Start with the ground unknown (`unknown_active` set): for a model swapped in while the ground was unknown,
        so that "known again" is said once the new model has explained a whole window of steps (and names the ground
        identified by then), not at the swap by construction, when the weights are still the prior."""
        self._latch.active = True

    @property
    def identified(self) -> bool:
        """Whether the current weights name a top ground: always with `first_top: tie`; with `established` once the
        evidence has established one (before, the weights are the posterior as it is, with no top)."""
        return self.config.first_top == "tie" or self._leader is not None

    @property
    def calibration(self) -> tuple[np.ndarray, np.ndarray]:
        """(online gain (2,) on the command change [s^0], extra residual std (2,) [m/s, rad/s]) fitted so far."""
        return self._gain(), np.sqrt(self._extra_var)

    def _gain(self) -> np.ndarray:
        return np.where(self._s_dd > 1e-9, self._s_de / np.maximum(self._s_dd, 1e-9), 0.0)

    def __len__(self) -> int:
        return len(self._rows)

    def observe(self, state: np.ndarray, command: np.ndarray, next_state: np.ndarray) -> None:
        """Add one step (as `TerrainEstimator.observe`) and update the posterior with it.

        Steps are taken as consecutive: the command change is against the previous step's command.
        """
        x = checked_vector("state", state, 5)
        u = checked_vector("command", command, 2)
        x1 = checked_vector("next_state", next_state, 5)
        v_nom, w_nom = velocity_step_exact(
            self.model.theta, x[3:4].copy(), x[4:5].copy(), u[0:1].copy(), u[1:2].copy(), self.model.dt
        )
        mean, latent = self._predictor.predict(np.array([[u[0], u[1], x[3], x[4]]]), with_var=True)
        y = np.array([x1[3] - v_nom[0], x1[4] - w_nom[0]])
        first = self._u_prev is None  # no previous command: the change is unknown (taken as 0)
        du = np.zeros(2) if first else u - self._u_prev
        self._u_prev = u
        mean = mean[0].reshape(self._m, 2)
        anchor = np.zeros((self._m, 2))
        if self._anchor_map is not None and self._anchor_map.covers(u):
            anchor = self._steady_bias(u)
            mean = mean - anchor
        gp_var = latent[0].reshape(self._m, 2) + self._noise
        # score with the calibration of the steps before this one, then update it with this one
        h = self.config.switch_prob
        prior = (1.0 - h) * self._posterior + h / self._m
        pred = mean + self._command_part(du)
        var = gp_var + self._extra_var
        if self.config.variance == "shared":
            # every terrain scored against the same spread: the likelihood-noise differences fitted on training drives
            # do not carry over to closed-loop steps, and as a signature they mislead (smooth driving on tile, whose
            # GP noise is twice asphalt's, then reads as asphalt on the log-determinant alone)
            var = np.broadcast_to(prior @ var, var.shape)
        r = y[None, :] - pred
        loglik = -0.5 * np.sum(np.log(2.0 * np.pi * var) + r * r / var, axis=1) / self.config.temperature
        if u[0] - x[3] > self.config.gp_max_speed_gap:  # a start from rest: see EstimatorConfig.gp_max_speed_gap
            loglik = np.zeros(self._m)
            self._since_start = 0
        else:
            self._since_start += 1
        if self.novelty is not None:  # the GP evidence's steps less the transients (gpmppi.terrain.novelty), on the
            # residuals the novelty test was calibrated on (without the anchor's correction: `mean` had the anchor
            # taken out, so r is the unanchored residual plus the anchor)
            one = self.novelty.observe(r - anchor, self.novelty.transient(u[0], x[3], x[4]))
            free, free_ready = 0.0, False
            if self.free_run is not None:  # either channel can say "unknown": no trained ground explains it
                free, free_ready = self.free_run.observe(x[3:5], u, x1[3:5]), self.free_run.ready
            self._unknown = max(one, free)
            self._channel = ("" if not (self.novelty.ready or free_ready) else
                             "free-run" if free > one or not self.novelty.ready else "one-step")
        # a held decision (`hold_unknown`) waits for a whole window of either channel
        if self.novelty is not None and (self.novelty.ready or (self.free_run is not None and self.free_run.ready)):
            self._latch.update(self._unknown)
        response = self._response_loglik(x, u, x1, du, first)  # run every step: its free run and average go on
        if self._since_start >= self.config.response_settle_steps:
            loglik = loglik + response
        log_post = np.log(prior) + loglik
        p = np.exp(log_post - log_post.max())
        self._calibrate(y, du, prior, mean, pred, gp_var)
        self._posterior = p / p.sum()
        self._rows.append((y, pred))
        self._seen += 1

    def _steady_bias(self, u: np.ndarray) -> np.ndarray:
        """(M, 2) each terrain's GP mean minus the one-step residual its measured steady state implies under `u`.

        At its steady state s_i(u) terrain i's next velocity is s_i(u), so its residual there is s_i(u) minus the
        nominal step from s_i(u); the GP, fitted on transient-rich drives and lacking the plant's hidden states,
        misses that by as much as the terrains differ (its fixed point is 25-49 mrad/s off). Taking this bias out
        of each terrain's prediction makes the GP evidence agree with the steady map where the robot drives steadily.
        """
        assert self._anchor_map is not None
        steady = self._anchor_map.steady_at(u)  # (M, 2)
        m = self._m
        inputs = np.column_stack([np.repeat(u[None, :], m, axis=0), steady])
        at_steady, _ = self._predictor.predict(inputs, with_var=False)
        own = at_steady.reshape(m, m, 2)[np.arange(m), np.arange(m)]  # terrain i's mean at its own steady state
        v_nom, w_nom = velocity_step_exact(self.model.theta, steady[:, 0].copy(), steady[:, 1].copy(),
                                           np.full(m, u[0]), np.full(m, u[1]), self.model.dt)
        return own - (steady - np.column_stack([v_nom, w_nom]))

    def _response_loglik(
        self, x: np.ndarray, u: np.ndarray, x1: np.ndarray, du: np.ndarray, first: bool
    ) -> np.ndarray:
        """(M,) each terrain's log-likelihood of the averaged response residual after this step (0 without one).

        Each terrain's response runs free under the applied commands from the measured velocity (re-anchored where
        a step does not start at the last one's end: a skipped transition); its residual against the measured next
        velocity is averaged exponentially over `response_smoothing_steps` and scored against `response_spread`,
        while the commands are smooth (`response_max_roughness`; `du` is the change since the previous command,
        unknown on the `first` step) and on the map's measured grid (`TerrainResponse.covers`).
        """
        if self._response is None:
            return np.zeros(self._m)
        off_grid = not self._response.covers(u)
        if self._response_pred is None or self._response_at is None or not np.array_equal(x, self._response_at):
            self._response_pred = np.tile(x[3:5], (self._m, 1))
        self._response_pred = self._response.step(self._response_pred, u)
        self._response_at = x1.copy()
        if not first:
            self._roughness_sum = 0.9 * self._roughness_sum + np.abs(du) / self.model.dt
            self._roughness_weight = 0.9 * self._roughness_weight + 1.0
            self._roughness_seen += 1
        if off_grid:
            # off the measured grid (a pivot at -2.5 rad/s against a grid to -2) the clamped map is off by tens of
            # nats a step for the terrains it gets wrong: no residual from such a step, and the free run starts
            # again from the measured velocity once back on the grid
            self._response_pred = None
            return np.zeros(self._m)
        if self._roughness_seen < ROUGHNESS_WARMUP_STEPS or np.any(
            self._roughness_sum / max(self._roughness_weight, 1e-12) > self._max_roughness
        ):
            return np.zeros(self._m)
        beta = 1.0 / self.config.response_smoothing_steps
        steady = self._response.steady_at(u)
        scored = np.max(np.abs(steady - x1[None, 3:5]), axis=0) <= self._max_transient  # (2,) per channel
        self._response_residual[:, scored] = ((1.0 - beta) * self._response_residual[:, scored]
                                              + beta * (x1[None, 3:5] - self._response_pred)[:, scored])
        self._response_pred[:, ~scored] = x1[None, 3:5][:, ~scored]
        return -0.5 * np.sum(((self._response_residual / self._response_spread) ** 2)[:, scored], axis=1)

    def _command_part(self, du: np.ndarray) -> np.ndarray:
        """(M, 2) the residual each terrain expects from the change of command `du` since the previous step."""
        if self.config.command_change == "per_terrain":
            return self._terrain_gains * du[None, :]
        if self.config.command_change == "online":
            return np.broadcast_to(self._gain() * du, (self._m, 2))
        return np.zeros((self._m, 2))

    def _calibrate(
        self, y: np.ndarray, du: np.ndarray, w: np.ndarray, mean: np.ndarray, pred: np.ndarray, gp_var: np.ndarray
    ) -> None:
        """Update the online command-change gain and the extra spread on the residual of the weighted prediction."""
        lam = 1.0 - 1.0 / self.config.calibration_steps
        e = y - w @ mean
        self._s_dd = lam * self._s_dd + du * du
        self._s_de = lam * self._s_de + du * e
        if not self.config.adapt_noise:
            return
        spread = (y - w @ pred) ** 2 - w @ gp_var  # what the GP's variance leaves unexplained
        self._calibrated = lam * self._calibrated + 1.0
        # the configured extra spread is the prior: it weighs as much as calibration_steps / 10 steps
        prior_n = 0.1 * self.config.calibration_steps
        prior_var = np.square(np.asarray(self.config.extra_noise_std, dtype=np.float64))
        self._sum_spread = lam * self._sum_spread + spread
        est = (prior_n * prior_var + self._sum_spread) / (prior_n + self._calibrated)
        self._extra_var = np.maximum(est, 0.0)

    def _published(self, p: np.ndarray) -> np.ndarray:
        """The posterior with hysteresis on which terrain leads.

        Where terrains explain the steps about equally their posteriors wander about each other, and the top
        terrain would change on every small wander. The terrain that led the last published weights keeps the lead
        until another's posterior exceeds its own by `hysteresis`; until then it and every terrain whose posterior
        is above its own are published at their mean, the leader on top (1e-6 above each of the others; the sum and
        every weight below the leader's unchanged). Holding the leader against the posterior's top terrain alone is
        not enough: near a uniform posterior a third terrain between the two would come out above their mean.

        With `hysteresis_odds` an established leader (one the evidence has put that many nats ahead of every other
        terrain) also needs the challenger `hysteresis_odds` nats ahead (log p_c - log p_l): a margin of 0.3 in
        probability is only 0.7 nats while a third terrain holds a third of the weight, and weak leads of that size
        took the top for a second or two on the lanes. A leader not yet established (the uniform start's tie, or one
        that took a tie's place on a weak lead) has only the probability margin, so the first identification does not
        wait on the margin.

        With `first_top: established` there is no leader until the evidence establishes one: the uniform start is a
        tie, and the tie's argmax (the profile's first ground) is no identification. Until a terrain is
        `hysteresis_odds` nats ahead of every other the posterior is published as it is (the planner mixes what the
        evidence says) and `identified` is False; the first top is then established, held as above.
        """
        leader = self._leader
        challenger = int(np.argmax(p))
        w = p.copy()
        logp = np.log(np.maximum(p, 1e-300))
        if leader is None and self.config.first_top == "established":
            if logp[challenger] - np.max(np.delete(logp, challenger)) < self.config.hysteresis_odds:
                return w  # no ground established yet: no top to hold
            self._leader, self._established = challenger, True
            return w
        margin = self.config.hysteresis_odds if self._established else 0.0
        if leader is not None and challenger != leader and (
            p[challenger] - p[leader] <= self.config.hysteresis or logp[challenger] - logp[leader] < margin
        ):
            above = np.flatnonzero(p > p[leader])  # the challenger and any terrain between it and the leader
            mid = (p[leader] + p[above].sum()) / (above.size + 1)
            w[above] = mid - 1e-6
            w[leader] = mid + 1e-6 * above.size
        else:
            if leader != challenger:
                self._established = False
            leader = challenger
        # a leader is established once the evidence puts it `hysteresis_odds` ahead of every other terrain: before,
        # the top was a tie's (the uniform start) or a weak lead's, and the first identification must not wait on it
        if not self._established and self.config.hysteresis_odds > 0:
            self._established = bool(logp[leader] - np.max(np.delete(logp, leader)) >= self.config.hysteresis_odds)
        self._leader = leader
        return w

    def estimate(self) -> TerrainEstimate:
        """The posterior over terrains (after `min_history` steps; before, the starting weights), with hysteresis."""
        if self._seen < self.min_history:
            return TerrainEstimate(self.weights, False, float("nan"),
                                   f"history too short ({self._seen} of {self.min_history} steps); keeping previous "
                                   "weights", 0.0, self._latch.active, identified=self.identified)
        self._weights = self._published(self._posterior)
        fit = float(sum(np.sum((y - self._weights @ pred) ** 2) for y, pred in self._rows))
        return TerrainEstimate(self.weights, True, fit, f"posterior after {self._seen} steps", self._unknown,
                               self._latch.active, self._channel,
                               identified=self.identified)


def make_estimator(model: GPModel, config: EstimatorConfig | None = None) -> EstimatorLike:
    """The estimator `config.method` names, built for `model` (either satisfies `EstimatorLike`)."""
    cfg = config or EstimatorConfig()
    if cfg.method == "paper":
        return TerrainEstimator(model, history=cfg.history, gamma=cfg.gamma, min_history=cfg.min_history)
    return BayesTerrainEstimator(model, cfg)
