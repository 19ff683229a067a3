"""Terrain and robot parameter sets for the physics plant, loaded from YAML and validated.

The shipped file `gpmppi/data/terrains.yaml` holds the Jackal-like robot and the terrains
tile, asphalt, grass (training) and sand (unseen). A terrain is a friction model per wheel:

    F = mu N tanh(|s|) s / |s|,   s = (slip_long / slip_scale_long, lateral_vel / slip_scale_lat)

(a smooth Coulomb law on the combined slip velocity, anisotropic through `mu_long`/`mu_lat`),
plus rolling resistance `rolling N` opposing the contact-point velocity.
"""

from __future__ import annotations

import re
from pathlib import Path

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from gpmppi.yaml_file import yaml_error

TERRAIN_FILE_VERSION = 1
TERRAIN_NAME = re.compile(r"[a-z][a-z0-9_-]*")


class TerrainFileError(ValueError):
    """A terrain file could not be read or is malformed; the message names the file and field."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


class TerrainParams(_Strict):
    """Wheel-ground interaction of one terrain."""

    mu_long: float = Field(gt=0, le=2.0, description="longitudinal friction coefficient [-]")
    mu_lat: float = Field(gt=0, le=2.0, description="lateral friction coefficient [-]")
    slip_scale_long: float = Field(gt=0, le=2.0, description="longitudinal slip speed at ~76% of peak force [m/s]")
    slip_scale_lat: float = Field(gt=0, le=2.0, description="lateral slip speed at ~76% of peak force [m/s]")
    rolling: float = Field(ge=0, le=0.5, description="rolling resistance coefficient (force / normal load) [-]")
    drag: float = Field(0.0, ge=0, le=50.0, description="speed-proportional resistance per wheel (grass, sand) [N s/m]")
    description: str = Field("", description="what this terrain stands for")


class RobotParams(_Strict):
    """A four-wheel skid-steer robot with one velocity-controlled motor per side (Jackal-like defaults)."""

    mass: float = Field(17.0, gt=0, description="total mass [kg]")
    yaw_inertia: float = Field(0.40, gt=0, description="yaw moment of inertia about the centre [kg m^2]")
    track: float = Field(0.37, gt=0, description="lateral distance between left and right wheels [m]")
    wheelbase: float = Field(0.26, gt=0, description="longitudinal distance between front and rear axles [m]")
    wheel_radius: float = Field(0.098, gt=0, description="wheel radius [m]")
    side_inertia: float = Field(0.04, gt=0, description="drivetrain inertia per side, at the wheel axis [kg m^2]")
    max_speed: float = Field(2.0, gt=0, description="wheel surface speed limit of the command mapping [m/s]")
    track_multiplier: float = Field(
        1.1, gt=0, description="effective-track factor of the command-to-wheel mapping (skid-steer compensation)"
    )
    motor_ref_time_constant: float = Field(
        0.25, gt=0, description="first-order lag of the motor drivers' wheel-speed setpoint [s]"
    )
    motor_kp: float = Field(20.0, gt=0, description="velocity loop proportional gain [N m / (rad/s)]")
    motor_ki: float = Field(200.0, ge=0, description="velocity loop integral gain [N m / rad]")
    motor_torque_max: float = Field(10.0, gt=0, description="stall torque per side at the wheel axis [N m]")
    motor_noload_speed: float = Field(
        3.2, gt=0, description="wheel surface speed where the available motor torque drops to zero [m/s]"
    )
    drivetrain_damping: float = Field(0.01, ge=0, description="viscous drivetrain friction per side [N m s]")
    noise_pos: float = Field(0.005, ge=0, description="measurement noise std on x, y [m]")
    noise_yaw: float = Field(0.003, ge=0, description="measurement noise std on yaw [rad]")
    noise_v: float = Field(0.008, ge=0, description="measurement noise std on forward velocity [m/s]")
    noise_omega: float = Field(0.01, ge=0, description="measurement noise std on yaw rate [rad/s]")
    internal_dt: float = Field(0.0005, gt=0, le=0.01, description="fixed integration step [s]")


class TerrainSet(_Strict):
    """The robot and the named terrains it may drive on."""

    version: int = Field(TERRAIN_FILE_VERSION, description="terrain file format version")
    robot: RobotParams = Field(default_factory=RobotParams)
    terrains: dict[str, TerrainParams] = Field(min_length=1)

    @model_validator(mode="after")
    def _check(self) -> TerrainSet:
        if self.version != TERRAIN_FILE_VERSION:
            raise ValueError(f"version {self.version} is not supported (this build reads {TERRAIN_FILE_VERSION})")
        bad = [n for n in self.terrains if not TERRAIN_NAME.fullmatch(n)]
        if bad:
            raise ValueError(f"terrain names {bad} must be lower-case words (letters, digits, '_' or '-')")
        return self

    def get(self, name: str) -> TerrainParams:
        """The terrain called `name`, with an error listing the known ones."""
        if name not in self.terrains:
            raise KeyError(f"unknown terrain {name!r}; this terrain set has {sorted(self.terrains)}")
        return self.terrains[name]

    @property
    def names(self) -> list[str]:
        return list(self.terrains)


def default_terrain_file() -> Path:
    """Path of the terrain file shipped with the package."""
    return Path(__file__).resolve().parents[1] / "data" / "terrains.yaml"


def load_terrains(path: str | Path | None = None) -> TerrainSet:
    """Read and validate a terrain file (None = the shipped one). Raises TerrainFileError naming file and field."""
    file = default_terrain_file() if path is None else Path(path)
    try:
        raw = yaml.safe_load(file.read_text())
    except OSError as exc:
        raise TerrainFileError(f"{file}: cannot read terrain file ({exc.strerror}); check the path") from exc
    except yaml.YAMLError as exc:
        raise TerrainFileError(yaml_error(file, exc)) from exc
    if not isinstance(raw, dict):
        raise TerrainFileError(f"{file}: expected a mapping with keys 'terrains' (and optionally 'robot', 'version')")
    try:
        return TerrainSet.model_validate(raw)
    except ValidationError as exc:
        problems = "; ".join(
            f"field {'.'.join(str(p) for p in err['loc']) or '<root>'}: {err['msg']}" for err in exc.errors()
        )
        raise TerrainFileError(f"{file}: invalid terrain file: {problems}") from exc
