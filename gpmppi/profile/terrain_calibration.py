"""What the terrain estimator learns about each ground of one robot, beside the GP: its calibration.

A `TerrainCalibration` is the part of a robot profile that the Bayesian terrain filter
(gpmppi.terrain.estimator) takes besides the GP: per ground the command-change gain (the GP residual per unit
change of command since the previous step, `command_change: per_terrain`) and the velocity response to a held
command (`response: steady_map`, gpmppi.profile.response). It is fitted from the robot's own logs, never from a
simulator, and is stored with the GP in the robot profile file (gpmppi.gp.model_file).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpmppi.profile.response import TerrainResponse


class CalibrationDataError(ValueError):
    """A log cannot calibrate a ground: the message names the ground, what was found, what is needed and what to
    drive."""


@dataclass(frozen=True)
class TerrainCalibration:
    """Per ground of one robot: the command-change gain and the velocity response, in the profile's ground order."""

    terrains: tuple[str, ...]  # (M,) ground names, the GP model's order
    command_gain: np.ndarray  # (M, 2) residual per unit change of command (v [m/s per m/s], omega [rad/s per rad/s])
    response: TerrainResponse  # steady map and rate of the same grounds, in the same order

    def __post_init__(self) -> None:
        m = len(self.terrains)
        if np.shape(self.command_gain) != (m, 2) or not np.all(np.isfinite(self.command_gain)):
            raise ValueError(f"terrain calibration: command_gain must be finite of shape {(m, 2)}, got "
                             f"{np.shape(self.command_gain)}")
        if tuple(self.response.terrains) != tuple(self.terrains):
            raise ValueError(f"terrain calibration: the response's grounds {list(self.response.terrains)} differ from "
                             f"the gains' {list(self.terrains)}")

    def select(self, names: list[str], source: str = "terrain calibration") -> TerrainCalibration:
        """The same calibration for `names` in that order; an error names any ground it does not hold."""
        missing = [t for t in names if t not in self.terrains]
        if missing:
            raise ValueError(f"{source}: no calibration for ground(s) {missing} (have {list(self.terrains)}); fit the "
                             "robot profile from logs that include them")
        idx = [self.terrains.index(t) for t in names]
        return TerrainCalibration(tuple(names), np.asarray(self.command_gain)[idx],
                                  self.response.select(list(names), source=source))
