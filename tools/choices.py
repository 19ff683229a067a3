"""Choices shared by several commands (typer needs Enums for fixed option values)."""

from __future__ import annotations

from enum import Enum


class ModelName(str, Enum):
    """The planner's rollout model (`PlannerConfig.dynamics`)."""

    gp = "gp"
    edd5 = "edd5"
    unicycle = "unicycle"


class FitSelection(str, Enum):
    """How `gpmppi train`'s fit chooses among its restarts and steps (`gpmppi.gp.fit.SELECTIONS`)."""

    fold = "fold"
    loo = "loo"
