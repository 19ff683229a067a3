"""Settings common to every service: how it joins the Zenoh network (`ZenohSettings`) and the fields every
service's settings share (`NodeSettings`: YAML file, then `GPMPPI_<FIELD>` environment overrides).

Kept apart from the node runtime so that the runtime's helpers (`scheduling`, `session`) can take settings
without importing the runtime that uses them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal, TypeVar

import zenoh
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, field_validator
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict, YamlConfigSettingsSource

from schemas.codec import MAX_PAYLOAD_BYTES
from schemas.keys import DEFAULT_ROBOT
from services.runtime.config_file import ConfigFileError, one_line, read_yaml, validation_problems

S = TypeVar("S", bound="NodeSettings")

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"


class ZenohSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    mode: Literal["client", "peer"] = Field("client", description="client of a router, or a peer")
    connect: list[str] = Field(default_factory=lambda: [DEFAULT_ROUTER], description="endpoints to connect to")
    listen: list[str] = Field(default_factory=list, description="endpoints to listen on (peers)")
    multicast_scouting: bool = Field(False, description="discover peers by UDP multicast (off: loopback only)")
    config_file: str | None = Field(None, description="a Zenoh json5 config applied before the fields above")
    # Zenoh's own connect retry (connect/retry/*): used while waiting for the router at start and to reconnect
    # after the router went away (a client re-opens its session to `connect` by itself, subscriptions included)
    retry_init_ms: int = Field(100, gt=0, description="first wait before retrying a connect (connect/retry) [ms]")
    retry_max_ms: int = Field(500, gt=0, description="longest wait between connect retries (connect/retry) [ms]")
    retry_factor: float = Field(2.0, ge=1.0, description="growth of the wait between connect retries")
    wait_for_router_s: float | None = Field(
        None, ge=0, description="how long a client waits at start for its router (None: until it appears or the "
        "service is stopped; 0: fail at once if it is not up)"
    )

    def to_config(self, connect_timeout_ms: int | None = None) -> zenoh.Config:
        """The Zenoh config; `connect_timeout_ms` sets connect/timeout_ms (0: one try; >0: retry that long)."""
        config = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        config.insert_json5("mode", json.dumps(self.mode))
        config.insert_json5("connect/endpoints", json.dumps(self.connect))
        config.insert_json5("listen/endpoints", json.dumps(self.listen))
        config.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        retry = {"period_init_ms": self.retry_init_ms, "period_max_ms": max(self.retry_max_ms, self.retry_init_ms),
                 "period_increase_factor": self.retry_factor}
        config.insert_json5("connect/retry", json.dumps(retry))
        if connect_timeout_ms is not None:
            config.insert_json5("connect/timeout_ms", json.dumps(connect_timeout_ms))
        return config


class NodeSettings(BaseSettings):
    """Settings common to every service. YAML file, then `GPMPPI_<FIELD>` environment overrides
    (nested with `__`, e.g. `GPMPPI_ZENOH__CONNECT='["tcp/127.0.0.1:7447"]'`)."""

    model_config = SettingsConfigDict(env_prefix="GPMPPI_", env_nested_delimiter="__", extra="forbid")

    service: str = Field("node", description="service name: health key, liveliness token, log prefix")
    robot: str = Field(DEFAULT_ROBOT, description="robot name, the second level of every key")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings, description="how to join the Zenoh network")
    heartbeat_hz: float = Field(1.0, gt=0, description="heartbeat rate on gpmppi/{robot}/health/{service}")
    poll_s: float = Field(
        0.05, gt=0, description="longest idle wait of the loop [s] (input wakes it at once; this bounds timers)"
    )
    nice: int = Field(
        0, ge=0, le=19, description="added to the process's niceness at start: a non-critical service (terrain, "
        "recorder, viewer) yields the cores to the control path (sim/ingress/planner/egress) on a small machine"
    )
    numba_threads: int | None = Field(
        None, description="threads of numba's parallel kernels in this process: n, or -k for all cores but k "
        "(at least 1); None: one per core"
    )
    max_payload_bytes: int = Field(MAX_PAYLOAD_BYTES, gt=0, description="larger payloads are rejected")
    log_level: str = Field("INFO", description="logging level")
    log_json: bool = Field(True, description="JSON-lines logs (False: plain text)")
    # the model file's (mtime, size) when `load` read the settings: a profile rewritten since (a ground learned
    # online) is a change a warm spare must not take over without (see `changed_since_loaded`)
    _model_stamp: tuple[int, int] | None = PrivateAttr(None)

    @field_validator("numba_threads")
    @classmethod
    def _nonzero_threads(cls, v: int | None) -> int | None:
        if v == 0:
            raise ValueError("numba_threads must be a thread count (>= 1), -k for all cores but k, or null")
        return v

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # precedence: explicit arguments > environment > YAML file (set by `load`) > defaults
        return init_settings, env_settings, YamlConfigSettingsSource(settings_cls)

    @classmethod
    def load(cls: type[S], path: str | Path | None = None, **overrides: Any) -> S:
        """Settings from a YAML file (if given) with environment and keyword overrides on top."""
        if path is None:
            return cls(**overrides)
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"config file {path} does not exist; pass an existing YAML file")
        # read here first, for one-line errors with the file's own lines (ConfigFileError), not a parser traceback
        data, marks = read_yaml(path)
        if data is not None and not isinstance(data, dict):
            kind = type(data).__name__
            raise ConfigFileError(f"{path}:1:1: the settings must be a mapping (field: value), not a {kind}")
        bound = type(cls.__name__, (cls,), {"model_config": {**cls.model_config, "yaml_file": str(path)}})
        try:
            settings = bound(**overrides)
        except ValidationError as exc:
            raise ConfigFileError(one_line(validation_problems(exc, path, marks))) from None
        settings._model_stamp = _file_stamp(getattr(settings, "model_file", None))
        return settings


def _file_stamp(path: object) -> tuple[int, int] | None:
    """(mtime [ns], size [bytes]) of the file at `path`; None for no path or no file."""
    try:
        st = Path(str(path)).stat() if isinstance(path, str | Path) else None
    except OSError:
        return None
    return None if st is None else (st.st_mtime_ns, st.st_size)


def changed_since_loaded(settings: NodeSettings) -> list[str]:
    """The fields (top level, by name) whose value in the settings' file and environment now differs from
    `settings`, which were loaded from them (`NodeSettings.load`) earlier: a warm spare loads its settings when it
    starts, which may be long before it takes over; a `model_file` whose file was rewritten since counts as changed
    (a learned ground: the spare holds the old profile). [] when nothing changed, or when they came from no file.
    ConfigFileError (one line) when the file no longer loads."""
    path = settings.model_config.get("yaml_file")
    if not path:
        return []
    now = type(settings).__bases__[0].load(str(path))  # `load` made the settings' class, bound to the file
    old, new = settings.model_dump(), now.model_dump()
    changed = sorted(k for k in old if old[k] != new.get(k))
    # the same model_file, rewritten (the terrain service saves a learned ground over it): the spare loaded the old
    if "model_file" not in changed and settings._model_stamp is not None and now._model_stamp != settings._model_stamp:
        changed.append("model_file (the file was rewritten)")
    return changed
