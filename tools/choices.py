"""Choices shared by several commands (typer needs Enums for fixed option values)."""

from __future__ import annotations

from enum import Enum


class ModelName(str, Enum):
    """The planner's rollout model (`PlannerConfig.dynamics`)."""

    gp = "gp"
    edd5 = "edd5"
    unicycle = "unicycle"


class FitMode(str, Enum):
    """What `gpmppi train`'s seed draws (`gpmppi.gp.train.FITS`)."""

    seeded = "seeded"
    stable = "stable"
