"""gpmppi messages: the single source of truth for what crosses a process boundary.

`schemas` imports only pydantic (and the standard library), so every process, tool and
test can depend on it without pulling in the algorithm.
"""

from schemas.codec import DecodeError, decode, encode
from schemas.keys import KEYS, key_for, model_for_key
from schemas.messages import (
    SCHEMA_VERSION,
    BaseCommand,
    Circle,
    Command,
    EStop,
    GroundLearn,
    Header,
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

__all__ = [
    "KEYS",
    "SCHEMA_VERSION",
    "BaseCommand",
    "Circle",
    "Command",
    "DecodeError",
    "EStop",
    "GroundLearn",
    "Header",
    "Heartbeat",
    "Message",
    "ModelUpdate",
    "OccupancyGrid",
    "Plan",
    "State",
    "Task",
    "TerrainLabel",
    "TerrainWeights",
    "decode",
    "encode",
    "key_for",
    "model_for_key",
]
