"""The novelty test's calibration (gpmppi/terrain/novelty.py, gpmppi/terrain/free_run.py), as a robot profile stores it.

Beside the GP and the terrain calibration a profile (gpmppi.gp.model_file) may hold how its novelty test turns the
evidence into P(unknown ground): the best ground's windowed mean one-step residual (`NoveltyCalibration`) and, since
version 2 of this record, the best ground's windowed mean free-run error over a horizon of steps (`FreeRunCalibration`,
the channel that sees a loss of grip). `gpmppi train` fits both on the logs it trains from. They live here, below the
estimator, so the profile file can read them without importing it. Stored in the profile's metadata (a few numbers):
`to_metadata` / `from_metadata`. A version 1 record (no `version` key: profiles trained before the free-run channel)
loads with `free_run` None, which the estimator reads as the stated default
(`gpmppi.terrain.free_run.DEFAULT_FREE_RUN`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NOVELTY_RECORD_VERSION = 2  # 1: the one-step test alone; 2: with the free-run channel (`free_run`)


def _probability(z: float, enter: float, width: float) -> float:
    return float(1.0 / (1.0 + np.exp(-np.clip((z - enter) / width, -50.0, 50.0))))


def _check_common(what: str, window_steps: int, spread: tuple[float, float], enter: float, width: float) -> None:
    if window_steps < 1:
        raise ValueError(f"{what} window_steps must be >= 1, got {window_steps}")
    if len(spread) != 2 or not all(np.isfinite(s) and s > 0 for s in spread):
        raise ValueError(f"{what} spread must be two finite numbers > 0, got {list(spread)}")
    if not (np.isfinite(enter) and enter > 0 and np.isfinite(width) and width > 0):
        raise ValueError(f"{what} enter and width must be finite and > 0, got {enter}, {width}")


@dataclass(frozen=True)
class FreeRunCalibration:
    """How the best ground's windowed mean free-run error is turned into P(unknown) (gpmppi/terrain/free_run.py)."""

    horizon_steps: int  # steps each ground's response is run free from a measured velocity before it is compared
    window_steps: int  # free-run errors the mean is taken over
    spread: tuple[float, float]  # the windowed mean's spread on known ground: v [m/s], omega [rad/s]
    enter: float  # the statistic (a length in units of `spread`) at which P(unknown) = 0.5
    width: float  # how fast P rises past `enter` (logistic scale, same units)
    source: str = "default"  # where the numbers come from (a profile's logs, or the stated default)

    def __post_init__(self) -> None:
        if self.horizon_steps < 1:
            raise ValueError(f"free-run horizon_steps must be >= 1, got {self.horizon_steps}")
        _check_common("free-run", self.window_steps, self.spread, self.enter, self.width)

    def probability(self, z: float) -> float:
        """P(unknown) from this channel at statistic `z`."""
        return _probability(z, self.enter, self.width)

    def to_metadata(self) -> dict:
        return {"horizon_steps": int(self.horizon_steps), "window_steps": int(self.window_steps),
                "spread": [float(s) for s in self.spread], "enter": float(self.enter), "width": float(self.width),
                "source": self.source}

    @classmethod
    def from_metadata(cls, data: object) -> FreeRunCalibration:
        if not isinstance(data, dict):
            raise ValueError(f"the free-run calibration must be a mapping, got {type(data).__name__}")
        try:
            return cls(int(data["horizon_steps"]), int(data["window_steps"]),
                       (float(data["spread"][0]), float(data["spread"][1])), float(data["enter"]),
                       float(data["width"]), str(data.get("source", "profile")))
        except (KeyError, TypeError, IndexError) as e:
            raise ValueError(f"the free-run calibration is incomplete ({e!r}); refit the profile") from e


@dataclass(frozen=True)
class NoveltyCalibration:
    """How the best ground's windowed mean residual is turned into P(unknown); with the free-run channel's own."""

    window_steps: int  # scored steps the residual mean is taken over
    spread: tuple[float, float]  # the windowed mean's spread on known ground: v [m/s], omega [rad/s]
    enter: float  # the statistic (a length in units of `spread`) at which P(unknown) = 0.5
    width: float  # how fast P rises past `enter` (logistic scale, same units)
    source: str = "default"  # where the numbers come from (a profile, or the stated default)
    # the free-run channel's calibration; None: a record made before it (the estimator takes the stated default)
    free_run: FreeRunCalibration | None = None

    def __post_init__(self) -> None:
        _check_common("novelty", self.window_steps, self.spread, self.enter, self.width)

    def probability(self, z: float) -> float:
        """P(unknown) at statistic `z`."""
        return _probability(z, self.enter, self.width)

    def to_metadata(self) -> dict:
        """The JSON-able form stored in a profile's metadata (version 2 when it holds the free-run channel's)."""
        out = {"window_steps": int(self.window_steps), "spread": [float(s) for s in self.spread],
               "enter": float(self.enter), "width": float(self.width), "source": self.source}
        if self.free_run is not None:
            out = {"version": NOVELTY_RECORD_VERSION, **out, "free_run": self.free_run.to_metadata()}
        return out

    @classmethod
    def from_metadata(cls, data: object) -> NoveltyCalibration:
        """Read it back (version 1 or 2); ValueError naming what is wrong."""
        if not isinstance(data, dict):
            raise ValueError(f"the novelty calibration must be a mapping, got {type(data).__name__}")
        version = data.get("version", 1)
        if version not in (1, NOVELTY_RECORD_VERSION):
            raise ValueError(f"the novelty calibration is version {version!r}, this build reads 1 and "
                             f"{NOVELTY_RECORD_VERSION}; update gpmppi or refit the profile with `gpmppi train`")
        try:
            free_run = (FreeRunCalibration.from_metadata(data["free_run"]) if version >= 2 and "free_run" in data
                        else None)
            return cls(int(data["window_steps"]), (float(data["spread"][0]), float(data["spread"][1])),
                       float(data["enter"]), float(data["width"]), str(data.get("source", "profile")), free_run)
        except (KeyError, TypeError, IndexError) as e:
            raise ValueError(f"the novelty calibration is incomplete ({e!r}); refit the profile") from e
