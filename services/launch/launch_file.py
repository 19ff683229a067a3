"""The launch file: which router and services a launch starts, how they join, and the restart policy.

Its own module so that the supervision (`services.launch.supervisor`) can take a launch file without importing the
launcher, which builds on the supervision."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from services.runtime.config_file import ConfigFileError, Marks, one_line, read_yaml, validation_problems
from services.runtime.node_settings import ZenohSettings

DEFAULT_LAUNCH = Path(__file__).resolve().parent / "default.yaml"


class RouterEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(True, description="start a router process (False: use an existing router or peers)")
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"], description="router endpoints")
    config: dict[str, Any] = Field(default_factory=dict, description="extra router settings")
    wait_s: float = Field(
        0.0, ge=0, description="enabled false: how long to wait for the outside router (0: it must be up at "
        "launch; >0: the services start at once and wait for it themselves, as under systemd)"
    )


class ServiceEntry(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(description="unique name of this process (service name in keys and logs)")
    kind: str | None = Field(None, description="which service to run (default: the name)")
    required: bool = Field(True, description="the launch fails when this service fails for good")
    enabled: bool = Field(True, description="start it at all")
    config: dict[str, Any] = Field(default_factory=dict, description="the service's settings")


class LaunchFile(BaseModel):
    model_config = ConfigDict(extra="forbid")
    robot: str = Field("jackal", description="robot name in every key")
    profile: str | None = Field(
        None, description="the robot profile (.npz from `gpmppi train`: GP, nominal model, terrain calibration) every "
        "service that loads the model runs with (planner, terrain; the recorder attaches it); a relative path is "
        "relative to the launch file. None: the shipped Jackal profile, or each service's own model_file"
    )
    router: RouterEntry = Field(default_factory=RouterEntry)
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings, description="how services join")
    services: list[ServiceEntry] = Field(default_factory=list)
    max_restarts: int = Field(
        3, ge=0, description="restarts in a row (each run shorter than restart_reset_s) before a service has "
        "failed for good"
    )
    restart_backoff_s: float = Field(
        0.25, gt=0, description="first restart delay [s]; doubles with each restart in a row (max 8 s)"
    )
    restart_reset_s: float = Field(
        30.0, gt=0, description="a service that ran this long before it died starts its backoff over [s]"
    )
    stop_timeout_s: float = Field(5.0, gt=0, description="wait after SIGINT, then after SIGTERM, before escalating")
    spares: list[str] | None = Field(
        None, description="services (by name) that get a warm spare: a second process, started ahead of need, that "
        "has loaded everything and waits (no session, no CPU) to take over the moment the service dies. None: every "
        "planner, terrain, ingress and egress service; []: none"
    )
    takeover_timeout_s: float = Field(
        10.0, gt=0, le=3600, description="a spare that got its go but has not joined (declared itself) this long "
        "after is killed, and its service restarts with backoff (a frozen or stuck spare is no single point of "
        "failure) [s]"
    )
    spare_delay_s: float = Field(
        5.0, ge=0, le=3600, description="a spare is made this long after its service (re)started, one spare "
        "warming at a time (planner first), so spares do not compete with a start for the CPU [s]"
    )
    spare_nice: int = Field(
        10, ge=0, le=19, description="a spare starts this much nicer (a lower CPU priority) than its service and "
        "takes the service's priority back when it takes over (that takes CAP_SYS_NICE or an RLIMIT_NICE allowing "
        "it, else it keeps the lower one and says so), so its start never takes the CPU from the control path it "
        "backs; 0: the same priority"
    )

    @classmethod
    def load(cls, path: str | Path) -> LaunchFile:
        """The launch file at `path`; `LaunchFileError` (one line, FILE:LINE:COL) if it does not parse or validate."""
        return load_launch(path)[0]


class LaunchFileError(ConfigFileError):
    """A launch file that cannot run as it is; the message is one line naming the file and the line."""


def load_launch(path: str | Path) -> tuple[LaunchFile, Marks]:
    """(the launch file, the line and column of each of its keys and list items). FileNotFoundError for a missing
    file; `LaunchFileError` for a YAML syntax error or a launch file that does not validate."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"launch file {path} does not exist")
    try:
        data, marks = read_yaml(path)
    except ConfigFileError as exc:
        raise LaunchFileError(str(exc)) from None
    if data is not None and not isinstance(data, dict):
        raise LaunchFileError(f"{path}:1:1: a launch file is a mapping (robot, router, services, ...), not a "
                              f"{type(data).__name__}")
    try:
        launch = LaunchFile.model_validate(data or {})
    except ValidationError as exc:
        raise LaunchFileError(one_line(validation_problems(exc, path, marks))) from None
    if launch.profile is not None:  # relative to the launch file, so a launch file and its profile move together
        launch.profile = str((path.parent / Path(launch.profile).expanduser()).resolve())
    return launch, marks


# the services that load the robot profile (their `model_file`, which a launch file's `profile` fills)
PROFILE_SERVICES = ("planner", "terrain")


def profile_configs(launch: LaunchFile, entries: list[ServiceEntry]) -> list[ServiceEntry]:
    """`entries` with the launch file's `profile` as the `model_file` of each service that loads the model and does
    not name its own."""
    if launch.profile is None:
        return entries
    return [e.model_copy(update={"config": {"model_file": launch.profile, **e.config}})
            if (e.kind or e.name) in PROFILE_SERVICES else e for e in entries]


def check_profile_grounds(launch: LaunchFile, path: str | Path) -> list[str]:
    """LaunchFileError (one line) when the launch file's `profile` is not a readable profile, lacks the terrain
    calibration a terrain service's estimator needs, or a service names a ground it lacks: the sim's `terrain`, a
    terrain service's `estimator.command_gains`. The sim's `terrain_switches` may name grounds the profile lacks
    (new ground, which the terrain service notices and learns): each is returned as a note for the launch log."""
    from gpmppi.gp.model_file import GPModel, ModelFileError
    from gpmppi.terrain.settings import EstimatorConfig, profile_calibration

    if launch.profile is None:
        return []
    try:
        model = GPModel.load(launch.profile)
        for e in launch.services:
            if e.enabled and (e.kind or e.name) == "terrain" and (e.config.get("estimator") or {}).get(
                    "method", "bayes") == "bayes":
                profile_calibration(EstimatorConfig.model_validate(e.config.get("estimator") or {}), model)
    except (ModelFileError, ValueError) as exc:
        raise LaunchFileError(f"{path}: profile: {exc}") from None
    grounds = list(model.terrains)
    notes: list[str] = []
    for e in launch.services:
        kind = e.kind or e.name
        named: list[str] = []
        if kind == "sim":
            from services.run import settings_class

            named = [str(e.config.get("terrain", settings_class("sim").model_fields["terrain"].default))]
            notes += [f"service {e.name!r} switches to ground {s.get('terrain')!r} {s.get('at_s')} s into the drive, "
                      "which the profile lacks: new ground" for s in e.config.get("terrain_switches") or []
                      if e.enabled and isinstance(s, dict) and s.get("terrain") not in grounds]
        elif kind == "terrain":
            named = [str(t) for t in ((e.config.get("estimator") or {}).get("command_gains") or {})]
        for ground in named:
            if e.enabled and ground not in grounds:
                raise LaunchFileError(
                    f"{path}: service {e.name!r} names ground {ground!r}, which the profile {launch.profile} lacks "
                    f"(its grounds: {grounds}); drive a ground the profile has, or fit one that has {ground!r} with "
                    "`gpmppi train`")
    return notes
