"""Zenoh key expressions, in one place, and which message lives on each."""

from __future__ import annotations

from schemas.messages import (
    BaseCommand,
    Command,
    EStop,
    GroundLearn,
    Heartbeat,
    Message,
    ModelUpdate,
    OccupancyGrid,
    Plan,
    State,
    Task,
    TerrainLabel,
    TerrainWeights,
)

DEFAULT_ROBOT = "jackal"

# name -> (key template, model). `{robot}` is the robot name; `{service}` the service name.
KEYS: dict[str, tuple[str, type[Message]]] = {
    "odom_raw": ("gpmppi/{robot}/odom/raw", State),
    "state": ("gpmppi/{robot}/state", State),
    "terrain_weights": ("gpmppi/{robot}/terrain/weights", TerrainWeights),
    "terrain_label": ("gpmppi/{robot}/terrain/label", TerrainLabel),
    "ground_learn": ("gpmppi/{robot}/terrain/learn", GroundLearn),
    "model_update": ("gpmppi/{robot}/model", ModelUpdate),
    "task": ("gpmppi/{robot}/task", Task),
    "costmap": ("gpmppi/{robot}/costmap", OccupancyGrid),
    "plan": ("gpmppi/{robot}/plan", Plan),
    "cmd": ("gpmppi/{robot}/cmd", Command),
    "base_cmd": ("gpmppi/{robot}/base/cmd", BaseCommand),
    "estop": ("gpmppi/{robot}/estop", EStop),
    "health": ("gpmppi/{robot}/health/{service}", Heartbeat),
}


def key_for(name: str, robot: str = DEFAULT_ROBOT, service: str = "*") -> str:
    """The concrete key expression for a key name, e.g. key_for("state") -> gpmppi/jackal/state."""
    if name not in KEYS:
        raise KeyError(f"unknown key name {name!r}; known: {sorted(KEYS)}")
    return KEYS[name][0].format(robot=robot, service=service)


def model_for_key(key: str) -> type[Message]:
    """The message model published on a concrete key, e.g. gpmppi/jackal/health/planner -> Heartbeat."""
    parts = key.split("/")
    for template, model in KEYS.values():
        tparts = template.split("/")
        if len(tparts) == len(parts) and all(
            t.startswith("{") or t == p for t, p in zip(tparts, parts, strict=True)
        ):
            return model
    raise KeyError(f"no message is registered for key {key!r}")
