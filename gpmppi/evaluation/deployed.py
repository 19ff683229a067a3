"""The deployed command path's settings, read from a launch file (`deploy/sim.yaml`, `deploy/robot.yaml`, the
default launch): egress's safety (`SafetyConfig`), the terrain service's cycle (`TerrainCycleConfig`, its
`command_source` among them), its estimator and the robot profile it names, so the evaluation runs what that launch
runs.

Checked at start: a value out of range, or a command source that does not exist, raises `DeployFileError` naming
the file, the service entry and the field, and what to do.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from gpmppi.safety import SafetyConfig
from gpmppi.terrain.cycle import TerrainCycleConfig
from gpmppi.terrain.settings import EstimatorConfig
from gpmppi.yaml_file import yaml_error


class DeployFileError(ValueError):
    """A launch file whose egress or terrain settings the evaluation cannot use."""


@dataclass(frozen=True)
class DeployedPath:
    safety: SafetyConfig | None  # None: the launch runs no egress
    terrain: TerrainCycleConfig = field(default_factory=TerrainCycleConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    source: str = "defaults"  # where they came from
    profile: str | None = None  # the launch file's robot profile (top-level `profile`, resolved), None: not named


def _entry(services: list[Any], kind: str, path: Path) -> tuple[int, dict[str, Any]] | None:
    """(index, config) of the enabled service entry of `kind` (its `kind`, or its name when it has none)."""
    for i, entry in enumerate(services):
        if not isinstance(entry, dict):
            raise DeployFileError(f"{path}: services[{i}] is not a mapping (name, config, ...)")
        if (entry.get("kind") or entry.get("name")) == kind and entry.get("enabled", True):
            config = entry.get("config") or {}
            if not isinstance(config, dict):
                raise DeployFileError(f"{path}: services[{i}] ({kind}).config is not a mapping")
            return i, config
    return None


def _validate(model: type[BaseModel], values: dict[str, Any], where: str) -> Any:
    try:
        return model.model_validate(values)
    except ValidationError as exc:
        problems = "; ".join(
            f"{where}{''.join('.' + str(p) for p in err['loc'])}: {err['msg']} (got {err.get('input')!r})"
            for err in exc.errors()
        )
        raise DeployFileError(f"{problems}; fix the value in the file (field descriptions: `gpmppi service "
                              f"--help` and docs/safety.md)") from None


def deployed_path(path: str | Path) -> DeployedPath:
    """The egress and terrain settings of the launch file at `path` (defaults for what it does not set)."""
    path = Path(path)
    if not path.is_file():
        raise DeployFileError(f"launch file {path} does not exist; pass an existing launch YAML (deploy/sim.yaml)")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise DeployFileError(yaml_error(path, exc)) from None
    services = data.get("services", []) if isinstance(data, dict) else None
    if not isinstance(services, list):
        raise DeployFileError(f"{path}: `services` must be a list of service entries")
    safety = None
    if (egress := _entry(services, "egress", path)) is not None:
        i, config = egress
        fields = {k: v for k, v in config.items() if k in SafetyConfig.model_fields}
        safety = _validate(SafetyConfig, fields, f"{path}: services[{i}] (egress).config")
    terrain, estimator = TerrainCycleConfig(), EstimatorConfig()
    if (entry := _entry(services, "terrain", path)) is not None:
        i, config = entry
        fields = {k: v for k, v in config.items() if k in TerrainCycleConfig.model_fields}
        terrain = _validate(TerrainCycleConfig, fields, f"{path}: services[{i}] (terrain).config")
        estimator = _validate(EstimatorConfig, config.get("estimator") or {},
                              f"{path}: services[{i}] (terrain).config.estimator")
    profile = data.get("profile")
    if profile is not None and not isinstance(profile, str):
        raise DeployFileError(f"{path}: `profile` must be the path of a robot profile (.npz), got {profile!r}")
    # relative to the launch file, as the launcher resolves it
    profile = None if profile is None else str((path.parent / Path(profile).expanduser()).resolve())
    return DeployedPath(safety, terrain, estimator, str(path), profile)
