"""Settings of the terrain-weight estimator (gpmppi.terrain.estimator): which method and its parameters.

Apart from the estimators so a service can validate its settings without importing the solver (cvxpy).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator

SHIPPED_COMMAND_GAINS = Path(__file__).resolve().parents[1] / "data" / "terrain_command_gains.yaml"


class EstimatorConfig(BaseModel):
    """The terrain-weight estimator's settings: which method and its parameters."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    method: Literal["paper", "bayes"] = Field(
        "bayes", description="'paper': the convex least-squares mixture over the last `history` steps with an L1 "
        "price on moving the weights; 'bayes': the recursive Bayesian filter over terrains with the GP's predictive "
        "variances (BayesTerrainEstimator)")
    history: int = Field(20, ge=1, description="paper: steps H in the weight problem; bayes: steps kept for the "
                         "reported fit residual only")
    gamma: float = Field(0.1, ge=0, description="paper: L1 price of moving the weights between solves (in units of "
                         "the noise-normalised mean squared residual per step)")
    min_history: int = Field(3, ge=1, description="steps observed before the first estimate (before: the starting "
                             "weights, ok False)")
    switch_prob: float = Field(0.01, gt=0, lt=1, description="bayes: prior probability per step that the ground "
                               "under the robot changes (bounds how sure the filter gets, so how fast it follows a "
                               "change)")
    temperature: float = Field(3.0, gt=0, description="bayes: each step's log-likelihood is divided by this (> 1: "
                               "trust a step less, for residuals correlated over steps or heavier-tailed than the "
                               "GP's noise)")
    extra_noise_std: tuple[float, float] = Field(
        (0.02, 0.04), description="bayes: residual std (v [m/s], omega [rad/s]) added to the GP's predictive spread "
        "(what the GP's noise leaves out on closed-loop steps); with adapt_noise the starting value of its online fit")
    variance: Literal["shared", "per_terrain"] = Field(
        "shared", description="bayes: score every terrain against the same predictive spread (the weighted mean of "
        "the terrains'), or each against its own")
    hysteresis: float = Field(
        0.3, ge=0, lt=1, description="bayes: another terrain takes the top weight only once its posterior exceeds "
        "the current top terrain's by this much (0: none)")
    # 2.5 nats (odds of 12 to 1), under half the most a leader can be ahead before a step's evidence (log(M /
    # switch_prob), 5.7 nats with three terrains), so a clearly identified ground always gets established. Measured
    # on three robots' Table 1 (27 cells, docs/terrain_identification.md "Identification targets on three robots"):
    # fewer top changes in three cells, no cell's weight moved beyond its runs' spread
    hysteresis_odds: float = Field(
        2.5, ge=0, allow_inf_nan=False, description="bayes: another terrain takes the top weight only once the log of "
        "its posterior over the top terrain's is at least this [nats], once the evidence has established the top "
        "(that many nats ahead of every other): a margin in the evidence's own units, the same whatever the other "
        "terrains hold (0: none)")
    # the uniform start is a tie, and a tie has no top: with "tie" the first published top is the profile's first
    # ground (the argmax of a tie), and the first identification of another ground counts as a change of the top
    first_top: Literal["tie", "established"] = Field(
        "established", description="bayes: when the published weights first name a top ground. 'tie': from the first "
        "estimate (the posterior's argmax; on the uniform start the profile's first ground); 'established': only once "
        "the evidence puts one ground `hysteresis_odds` nats ahead of every other (needs hysteresis_odds > 0), the "
        "same margin a switch needs; before, the weights are the posterior as it is and name no top "
        "(`TerrainEstimate.identified` False)")
    adapt_noise: bool = Field(True, description="bayes: fit the extra residual spread online")
    command_change: Literal["per_terrain", "online", "none"] = Field(
        "per_terrain", description="bayes: how each terrain's prediction takes in the change of command since the "
        "previous step (motor setpoint lag): per-terrain gains fitted offline (`command_gains`), one gain fitted "
        "online for all terrains, or not at all")
    command_gains: dict[str, tuple[float, float]] | None = Field(
        None, description="bayes, command_change per_terrain: per terrain the residual per unit change of command "
        "(v [m/s per m/s], omega [rad/s per rad/s]); None: the robot profile's calibration (fitted from its logs by "
        "`gpmppi train`)")
    calibration_steps: float = Field(100.0, ge=2, description="bayes: steps over which the online fits forget")
    response: Literal["steady_map", "none"] = Field(
        "steady_map", description="bayes: also score each terrain by its velocity response to the commands "
        "(gpmppi.profile.response: steady-state map and rate, run free from the measured velocity), which is "
        "unbiased at steady driving where the GP's one-step residuals are not; 'none': the GP evidence only")
    response_file: str | None = Field(
        None, description="bayes, response steady_map: a terrain response YAML (written by `gpmppi evaluate "
        "terrain-response`) instead of the robot profile's; None: the profile's calibration (`gpmppi train`)")
    response_smoothing_steps: float = Field(
        35.0, ge=1, description="bayes, response steady_map: steps over which the response residual is averaged "
        "(exponentially) before it is scored: the fast transients a first-order response gets wrong average out, "
        "a steady offset stays")
    response_max_roughness: tuple[float, float] = Field(
        (2.5, 5.0), description="bayes, response steady_map: the response is scored only while the commands' "
        "roughness (mean |du|/dt over the last ~10 steps; v [m/s^2], omega [rad/s^2]) stays below this: under "
        "jittery commands (the paper's update: ~5 and ~19) a first-order response is biased, under the smooth "
        "default (~0.5 and ~1.3) it is not")
    response_max_transient: tuple[float, float] = Field(
        (0.1, float("inf")), description="bayes, response steady_map: each channel of the response (v [m/s], omega "
        "[rad/s]) is scored only while the measured velocity lies within this of every terrain's steady state under "
        "the command; further off (the start from rest: the plant's PI integrators and torque limit, which a "
        "first-order rate leaves out) the channel's free run starts again from the measured velocity. inf: always")
    gp_max_speed_gap: float = Field(
        0.3, gt=0, description="bayes: no GP evidence from a step whose v command exceeds the measured speed by more "
        "than this [m/s] (the start from rest: the plant's hidden states, which the GP's inputs lack, are far from "
        "where its training drives had them). inf: never")
    gp_anchor: bool = Field(
        False, description="bayes: take out of each terrain's GP mean its bias at the terrain's measured steady state "
        "under the command (the residual its steady map, from the robot profile or `response_file`, implies there; "
        "also with response: none), so that the GP evidence agrees with the map where the robot drives steadily")
    response_settle_steps: int = Field(
        0, ge=0, description="bayes, response steady_map: steps after the last one the start gate held "
        "(gp_max_speed_gap), and after a reset, whose response is not scored (its free run and average go on): the "
        "first maneuvers after a start, where the first-order omega response misreads the swerves; 0: none")
    response_spread: tuple[float, float] = Field(
        (0.08, 0.016), description="bayes, response steady_map: the spread (v [m/s], omega [rad/s]) the averaged "
        "response residual is scored against (smaller: trust it more)")

    novelty: bool = Field(
        True, description="bayes: also test how well the best trained ground explains the recent steps at all and "
        "publish P(unknown ground) (gpmppi/terrain/novelty.py; calibrated by the robot profile, else a stated "
        "default)")
    novelty_free_run: bool = Field(
        True, description="bayes, with novelty: also test how well the best trained ground's velocity response, run "
        "free for a horizon of steps, ends where the robot is (gpmppi/terrain/free_run.py: sees a loss of grip the "
        "one-step test cannot); P(unknown) is the larger of the two channels'. Needs the profile's response map")
    novelty_grip_demand: float = Field(
        1.2, ge=0.0, description="bayes, free-run channel: the sideways acceleration |v_ref omega_ref| [m/s^2] a free "
        "run's commands must ask for (at one step at least) for its error to count towards 'known again': the "
        "channel's P(unknown) falls only once a window of such runs, driven after the alarm, is explained by a "
        "trained ground, so an alarm raised in a corner holds through the straights, where a slide cannot show "
        "(gpmppi/terrain/free_run.py). 0: no hold (the plain window alone)")

    @property
    def names_top_at_start(self) -> bool:
        """Whether the starting weights (the uniform prior, or weights resumed after a restart) name a top ground: the
        paper's method always names its weights' argmax; the Bayesian filter with `first_top: established` names none
        until the evidence establishes one (`BayesTerrainEstimator.identified`)."""
        return self.method == "paper" or self.first_top == "tie"

    @model_validator(mode="after")
    def _consistent(self) -> EstimatorConfig:
        if self.first_top == "established" and self.hysteresis_odds <= 0:
            raise ValueError("first_top 'established' (the default) needs hysteresis_odds > 0 (the margin that "
                             "establishes a top); set first_top: tie for no margin")
        if self.min_history > self.history:
            raise ValueError(f"min_history ({self.min_history}) must be <= history ({self.history})")
        if any(not (np.isfinite(s) and s >= 0) for s in self.extra_noise_std):
            raise ValueError(f"extra_noise_std must be two finite numbers >= 0, got {list(self.extra_noise_std)}")
        if any(not (np.isfinite(s) and s > 0) for s in self.response_spread):
            raise ValueError(f"response_spread must be two finite numbers > 0, got {list(self.response_spread)}")
        if any(not (s > 0) for s in self.response_max_transient):  # inf allowed: always score
            raise ValueError(f"response_max_transient must be two numbers > 0, got {list(self.response_max_transient)}")
        if any(not (s > 0) for s in self.response_max_roughness):  # inf allowed: always score
            raise ValueError(f"response_max_roughness must be two numbers > 0, got {list(self.response_max_roughness)}")
        return self


def load_command_gains(path: Path | str = SHIPPED_COMMAND_GAINS) -> dict[str, tuple[float, float]]:
    """Per-terrain command-change gains from a YAML file (`gains: {terrain: [g_v, g_omega]}`)."""
    try:
        data = yaml.safe_load(Path(path).read_text())
        gains = {str(k): (float(v[0]), float(v[1])) for k, v in data["gains"].items()}
    except (OSError, KeyError, TypeError, IndexError, ValueError, yaml.YAMLError) as e:
        raise ValueError(f"command gains file {path}: expected 'gains: {{terrain: [g_v, g_omega]}}' ({e})") from e
    if not all(np.isfinite(g).all() for g in gains.values()):
        raise ValueError(f"command gains file {path}: gains must be finite")
    return gains


def terrain_command_gains(config: EstimatorConfig, terrains: list[str]) -> np.ndarray:
    """(M, 2) the gains of `terrains` (the model's, in order) from `config.command_gains` or the shipped file (the
    estimator takes the robot profile's instead of the shipped file: `profile_calibration`)."""
    gains = config.command_gains if config.command_gains is not None else load_command_gains()
    missing = [t for t in terrains if t not in gains]
    if missing:
        raise ValueError(f"command_gains: no gain for terrain(s) {missing} (have {sorted(gains)}); fit them with "
                         "`gpmppi evaluate terrain-gains`, or set command_change: online")
    return np.array([gains[t] for t in terrains], dtype=np.float64)


def profile_calibration(config: EstimatorConfig, model):  # noqa: ANN001, ANN201 - GPModel, (gains, response | None)
    """(the (M, 2) command-change gains, the `TerrainResponse` or None) the Bayesian filter runs with, in the order
    of `model.terrains`: the explicit `command_gains` / `response_file` where set, else the robot profile's
    calibration (`model.require_calibration()`: a model without one is refused in one line naming its file)."""
    from gpmppi.profile.response import load_response

    names = list(model.terrains)
    gains, response = np.zeros((len(names), 2)), None
    if config.command_change == "per_terrain":
        gains = (terrain_command_gains(config, names) if config.command_gains is not None
                 else np.array(model.require_calibration().command_gain, dtype=np.float64))
    if config.response == "steady_map":
        if config.response_file is not None:
            path = config.response_file
            response = load_response(path).select(names, source=f"response_file {path}")
        else:
            response = model.require_calibration().response
    return gains, response


def shipped_calibration(terrains: list[str]):  # noqa: ANN201 - TerrainCalibration (imported here: no cycle)
    """The plant-fitted calibration of the simulated Jackal's grounds `terrains` (in that order) from the shipped
    YAMLs (gpmppi/data/terrain_command_gains.yaml, terrain_response.yaml, written by `gpmppi evaluate terrain-gains`
    and `terrain-response`): what synthetic test models carry. A robot's own comes from its logs (`gpmppi train`)."""
    from gpmppi.profile.response import load_response
    from gpmppi.profile.terrain_calibration import TerrainCalibration

    names = list(terrains)
    gains = terrain_command_gains(EstimatorConfig(), names)
    return TerrainCalibration(tuple(names), gains, load_response().select(names, source="shipped terrain response"))
