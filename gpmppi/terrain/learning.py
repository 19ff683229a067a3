"""The terrain service's learning of a new ground, free of transport and threads: when to collect, what, when to fit.

`GroundLearning` is told to start (a `GroundLearn` message: the user's label, or '' for the next `new-N`; later also
the estimator's `unknown` probability above `unknown_threshold` for `unknown_hold_s`), collects the steps the
estimator observes (`TeeEstimator` hands them over, so it sees exactly the estimator's pairing and gating), and once
it holds `steps` of them hands out a fit job (`take_job`). The service runs the job off its cycle
(services/terrain_learning.py) and reports back (`finished` / `failed`). One ground is learned at a time.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, Field

from gpmppi.gp.model_file import GPModel
from gpmppi.gp.online_ground import GroundSamples, LearnSettings, next_name
from gpmppi.terrain.estimate import EstimatorLike, TerrainEstimate

Phase = Literal["idle", "collecting", "fitting"]


class LearnConfig(BaseModel):
    """Learning a new ground while driving (the terrain service's `learn` settings)."""

    enabled: bool = Field(True, description="take GroundLearn requests (and, with the novelty test, unknown ground)")
    steps: int = Field(600, ge=10, le=36000, description="steps collected before the fit (10 Hz: 600 = 60 s) [steps]")
    min_samples: int = Field(300, ge=10, description="fewer steps than this make no ground: refused, and logged why")
    max_points: int = Field(150, ge=10, le=600, description="conditioning inputs of the new ground's GP")
    hyperparameters: Literal["kept", "fitted"] = Field(
        "kept", description="'kept': the nearest trained ground's, with its mean as the prior; 'fitted': fitted on "
        "the samples (GPyTorch) (gpmppi/gp/online_ground.py)")
    iters: int = Field(100, ge=1, description="'fitted': optimizer steps")
    seed: int = Field(0, ge=0, description="seed of the k-means selection and the fit")
    save_to: str | None = Field(None, description="where the learned profile is saved (None: over the service's "
                                "model_file, so a restart keeps it)")
    unknown_threshold: float = Field(0.5, gt=0, le=1, description="start learning when the estimator's `unknown` "
                                     "probability stays above this (needs the novelty test)")
    unknown_hold_s: float = Field(3.0, ge=0, description="... for this long [s]")

    def learn_settings(self) -> LearnSettings:
        return LearnSettings(min_samples=self.min_samples, max_points=self.max_points,
                             hyperparameters=self.hyperparameters, iters=self.iters, seed=self.seed)


@dataclass
class FitJob:
    """What a fit needs: the profile to extend, the new ground's name and steps, how to fit."""

    model: GPModel | None  # None: read from `model_path` (`profile()`)
    name: str
    x: np.ndarray  # (N, 4) GP inputs
    y: np.ndarray  # (N, 2) residuals
    du: np.ndarray  # (N, 2) command changes
    settings: LearnSettings
    steps: np.ndarray | None = None  # (N, 12) each step: state (5), command (2), next state (5) (None: not kept)
    model_path: str | None = None  # the profile's file, when `model` travels by it (`for_process`)

    def for_process(self) -> FitJob:
        """The job as another process takes it: the profile by its file where it has one (tens of MB of arrays,
        whose pickling would hold the sender for seconds), else as it is."""
        path = None if self.model is None else self.model.source
        if path is None or not Path(path).is_file():
            return self
        return dataclasses.replace(self, model=None, model_path=path)  # type: ignore[arg-type]

    def profile(self) -> GPModel:
        """The profile to extend (read from `model_path` when it came by file)."""
        if self.model is None:
            assert self.model_path is not None
            self.model = GPModel.load(self.model_path)
        return self.model

    def samples(self) -> GroundSamples:
        model = self.profile()
        s = GroundSamples(model.theta, model.dt)
        s.x, s.y, s.du = list(self.x), list(self.y), list(self.du)
        return s


class GroundLearning:
    """Collects one new ground's steps on request and hands out its fit (see the module docstring)."""

    def __init__(self, model: GPModel, config: LearnConfig) -> None:
        self.model = model
        self.config = config
        self.phase: Phase = "idle"
        self.name = ""
        self.samples: GroundSamples | None = None
        self._unknown_since: float | None = None
        self._known_since: float | None = None
        self._auto = False  # the collection was started by unknown ground, not by a request

    def start(self, name: str = "") -> str:
        """Start collecting the ground under the robot as `name` ('' : the next `new-N`); what happened, in words."""
        if not self.config.enabled:
            return "learning is disabled (learn.enabled: false): request ignored"
        if self.phase != "idle":
            return f"already learning {self.name!r} ({self.phase}): request ignored"
        name = name.strip() or next_name(self.model)
        if not re.fullmatch(r"[A-Za-z0-9_-]{1,64}", name):
            return f"ground name {name!r}: use 1-64 letters, digits, '_' or '-'; request ignored"
        if name in self.model.terrains:
            return f"ground {name!r} is already in the profile: request ignored; name the new ground differently"
        self.phase, self.name, self._auto = "collecting", name, False
        self.samples = GroundSamples(self.model.theta, self.model.dt)
        return f"learning ground {name!r}: collecting {self.config.steps} steps"

    def cancel(self) -> str:
        if self.phase != "collecting":
            return f"nothing to cancel ({self.phase})"
        name, self.phase, self.samples = self.name, "idle", None
        return f"learning {name!r} cancelled"

    def on_unknown(self, unknown: float, now: float) -> str | None:
        """The estimator's `unknown` probability at `now` [s]: starts learning once it stays above the threshold for
        `unknown_hold_s`, and drops a collection it started so once the probability stays at or below the threshold
        as long (the ground was known after all: a transient, such as a start from rest, and not new ground; a
        collection a request started is kept); what happened, in words, else None."""
        hold = self.config.unknown_hold_s
        if unknown <= self.config.unknown_threshold:
            self._unknown_since = None
            self._known_since = now if self._known_since is None else self._known_since
            if self.phase == "collecting" and self._auto and now - self._known_since >= hold:
                collected = 0 if self.samples is None else len(self.samples)
                name, self.phase, self.samples, self._auto = self.name, "idle", None, False
                return (f"ground known again for {hold:.1f} s: learning {name!r} dropped ({collected} steps "
                        "collected), it was no new ground")
            return None
        self._known_since = None
        if self._unknown_since is None:
            self._unknown_since = now
        if self.phase == "idle" and now - self._unknown_since >= hold:
            started = self.start("")
            self._auto = self.phase == "collecting"
            return f"ground unknown for {hold:.1f} s: {started}"
        return None

    def observe(self, state: np.ndarray, command: np.ndarray, next_state: np.ndarray) -> None:
        if self.phase == "collecting" and self.samples is not None:
            self.samples.add(state, command, next_state)

    def take_job(self) -> FitJob | None:
        """The fit, once `steps` are collected (then the phase is 'fitting' until `finished` or `failed`)."""
        if self.phase != "collecting" or self.samples is None or len(self.samples) < self.config.steps:
            return None
        x, y, du = self.samples.arrays()
        steps = np.stack(self.samples.steps)
        self.phase, self.samples = "fitting", None
        return FitJob(self.model, self.name, x, y, du, self.config.learn_settings(), steps)

    def finished(self, model: GPModel) -> None:
        """The fit is in: later requests extend `model`."""
        self.model, self.phase, self.name = model, "idle", ""

    def failed(self) -> None:
        self.phase, self.name = "idle", ""


class TeeEstimator:
    """An estimator that also hands every step it observes to a `GroundLearning` (same pairing, same gating)."""

    def __init__(self, estimator: EstimatorLike, learning: GroundLearning) -> None:
        self.estimator = estimator
        self.learning = learning
        self.min_history = estimator.min_history

    @property
    def weights(self) -> np.ndarray:
        return self.estimator.weights

    def observe(self, state: np.ndarray, command: np.ndarray, next_state: np.ndarray) -> None:
        self.estimator.observe(state, command, next_state)
        self.learning.observe(state, command, next_state)

    def estimate(self) -> TerrainEstimate:
        return self.estimator.estimate()

    def reset(self, weights: np.ndarray | None = None) -> None:
        reset = getattr(self.estimator, "reset", None)
        if reset is not None:
            reset(weights)

    def __len__(self) -> int:
        return len(self.estimator)
