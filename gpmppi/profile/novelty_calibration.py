"""The novelty test's calibration (gpmppi/terrain/novelty.py), as a robot profile stores it.

Beside the GP and the terrain calibration a profile (gpmppi.gp.model_file) may hold how its novelty test turns the
best ground's windowed mean residual into P(unknown ground): `gpmppi train` fits it on the logs it trains from
(`gpmppi.terrain.novelty.calibrate`). It lives here, below both, so the profile file can read it without importing
the estimator. Stored in the profile's metadata (a few numbers): `to_metadata` / `from_metadata`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class NoveltyCalibration:
    """How the best ground's windowed mean residual is turned into P(unknown)."""

    window_steps: int  # scored steps the residual mean is taken over
    spread: tuple[float, float]  # the windowed mean's spread on known ground: v [m/s], omega [rad/s]
    enter: float  # the statistic (a length in units of `spread`) at which P(unknown) = 0.5
    width: float  # how fast P rises past `enter` (logistic scale, same units)
    source: str = "default"  # where the numbers come from (a profile, or the stated default)

    def __post_init__(self) -> None:
        if self.window_steps < 1:
            raise ValueError(f"novelty window_steps must be >= 1, got {self.window_steps}")
        if len(self.spread) != 2 or not all(np.isfinite(s) and s > 0 for s in self.spread):
            raise ValueError(f"novelty spread must be two finite numbers > 0, got {list(self.spread)}")
        if not (np.isfinite(self.enter) and self.enter > 0 and np.isfinite(self.width) and self.width > 0):
            raise ValueError(f"novelty enter and width must be finite and > 0, got {self.enter}, {self.width}")

    def probability(self, z: float) -> float:
        """P(unknown) at statistic `z`."""
        return float(1.0 / (1.0 + np.exp(-np.clip((z - self.enter) / self.width, -50.0, 50.0))))

    def to_metadata(self) -> dict:
        """The JSON-able form stored in a profile's metadata."""
        return {"window_steps": int(self.window_steps), "spread": [float(s) for s in self.spread],
                "enter": float(self.enter), "width": float(self.width), "source": self.source}

    @classmethod
    def from_metadata(cls, data: object) -> NoveltyCalibration:
        """Read it back; ValueError naming what is wrong."""
        if not isinstance(data, dict):
            raise ValueError(f"the novelty calibration must be a mapping, got {type(data).__name__}")
        try:
            return cls(int(data["window_steps"]), (float(data["spread"][0]), float(data["spread"][1])),
                       float(data["enter"]), float(data["width"]), str(data.get("source", "profile")))
        except (KeyError, TypeError, IndexError) as e:
            raise ValueError(f"the novelty calibration is incomplete ({e!r}); refit the profile") from e
