"""JSON on the wire (`application/json`): encode a message, decode bytes with clear errors."""

from __future__ import annotations

from typing import TypeVar

from pydantic import ValidationError

from schemas.messages import Message

ENCODING = "application/json"
MAX_PAYLOAD_BYTES = 4 * 1024 * 1024

M = TypeVar("M", bound=Message)


class DecodeError(ValueError):
    """A payload that is not a valid message of the expected type."""


def encode(msg: Message) -> bytes:
    return msg.model_dump_json().encode()


def decode(model: type[M], payload: bytes | bytearray | memoryview, max_bytes: int = MAX_PAYLOAD_BYTES) -> M:
    data = bytes(payload)
    if len(data) > max_bytes:
        raise DecodeError(f"{model.__name__}: payload of {len(data)} bytes exceeds the {max_bytes} byte limit")
    try:
        return model.model_validate_json(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ())) or "<root>"
        raise DecodeError(
            f"{model.__name__}: invalid at {where}: {first.get('msg')} ({exc.error_count()} error(s))"
        ) from exc
