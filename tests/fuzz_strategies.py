"""Hypothesis strategies for hostile and extreme payloads: messages built from the pydantic models' own fields
(with NaN, infinity, 1e6 and 1e308, huge and empty arrays, wrong types, missing and unknown fields, wrong
schema versions), and junk (random bytes, invalid JSON, deep nesting, other text encodings, oversize).

A generated message is a dict; the string NOW in a header's stamp is replaced by the current time when it is
sent (`materialize`), so a valid-but-extreme message is also fresh enough to get past the stale-input checks."""

from __future__ import annotations

import gzip
import json
import math
import time
import types
import typing
from typing import Annotated, Any, Literal, Union

from hypothesis import strategies as st
from pydantic import BaseModel

from schemas import Header, Message, Plan, State, Task
from schemas.codec import MAX_PAYLOAD_BYTES

NOW = "__now__"

EXTREME_FLOATS = [0.0, -0.0, 1.0, -1.0, 1e6, -1e6, 1e-300, 5e-324, 1e308, -1e308, math.nan, math.inf, -math.inf]
floats = st.one_of(st.sampled_from(EXTREME_FLOATS), st.floats(-1e3, 1e3, allow_nan=False))
ints = st.one_of(st.sampled_from([0, -1, 1, 2**31, 2**63, 2**64 + 1, -(2**63)]), st.integers(-10, 10**6))
text = st.text(max_size=12)
wrong_type = st.one_of(st.none(), st.booleans(), st.just("x"), st.just([]), st.just({}), st.just("NaN"))


def _length(info: Any) -> tuple[int, int | None]:
    lo, hi = 0, None
    for m in getattr(info, "metadata", []) or []:
        lo = getattr(m, "min_length", None) or lo
        hi = getattr(m, "max_length", None) or hi
    return lo, hi


def value_for(annotation: Any, min_len: int = 0, max_len: int | None = None, depth: int = 0) -> st.SearchStrategy:
    """Values for a field of this type: mostly of the type (extremes included), sometimes of another."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is Annotated:
        lo, hi = _length(args[1])
        return value_for(args[0], lo, hi, depth)
    if origin is Literal:
        return st.one_of(st.sampled_from(args), text)
    if origin in (Union, types.UnionType):
        return st.one_of(*(value_for(a, min_len, max_len, depth) for a in args))
    if annotation is type(None):
        return st.none()
    if origin is list:
        # around the allowed length: one short, in range, one long, empty, and (rarely) huge
        item = value_for(args[0], depth=depth + 1)
        sizes = sorted({0, 1, max(0, min_len - 1), min_len, min_len + 1, max_len or 3, (max_len or 3) + 1})
        small = st.sampled_from(sizes).flatmap(lambda n: st.lists(item, min_size=n, max_size=n))
        return st.one_of(small, wrong_type) if depth else small
    if origin is dict:
        return st.dictionaries(text, value_for(args[1], depth=depth + 1), max_size=3)
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return model_dicts(annotation, depth + 1)
    base = {float: floats, int: ints, str: text, bool: st.booleans()}.get(annotation)
    if base is None:
        raise TypeError(f"no strategy for {annotation!r}")
    return st.one_of(base, wrong_type) if depth else st.one_of(base, base, base, wrong_type)


headers = st.fixed_dictionaries(
    {
        "stamp_ns": st.one_of(st.just(NOW), st.just(NOW), st.just(NOW), ints),
        "frame_id": st.sampled_from(["map", "odom", "", "\x00", "é" * 50]),
        "seq": ints,
        "schema_version": st.sampled_from([1, 1, 1, 1, 0, 2, 3, 4, 5, -1, 10**9, "1", None]),
    }
)


@st.composite
def model_dicts(draw: st.DrawFn, model: type[BaseModel], depth: int = 0) -> dict:
    """A dict shaped like `model`: each field from its own type, some fields dropped, sometimes an unknown one."""
    out: dict[str, Any] = {}
    for name, info in model.model_fields.items():
        if name == "header":
            if draw(st.integers(0, 9)):
                out[name] = draw(headers)
            continue
        if not info.is_required() and draw(st.integers(0, 2)) == 0:
            continue  # leave an optional field out
        if info.is_required() and draw(st.integers(0, 19)) == 0:
            continue  # leave a required field out: rejected
        lo, hi = _length(info)
        out[name] = draw(value_for(info.annotation, lo, hi, depth))
    if draw(st.integers(0, 14)) == 0:
        out["unexpected_field"] = 1
    return out


def valid_state(draw_float: st.SearchStrategy = floats) -> st.SearchStrategy:
    """A State with every field present and fresh, its values from `draw_float` (extremes by default)."""
    return st.builds(
        lambda x, y, th, v, w: {"header": {"stamp_ns": NOW}, "x": x, "y": y, "theta": th, "v": v, "omega": w},
        draw_float, draw_float, draw_float, draw_float, draw_float,
    )


# valid-but-extreme tasks: one-point and repeated-point polylines, far and huge coordinates, tiny widths
points = st.lists(st.tuples(floats, floats).map(list), min_size=1, max_size=4)
extreme_tasks = st.one_of(
    st.builds(lambda c, hw, sp, closed: {"kind": "lane", "centerline": c, "half_width": hw, "speed_target": sp,
                                         "closed": closed},
              st.one_of(points, st.just([[0.0, 0.0], [0.0, 0.0]]), st.just([[1e6, 1e6], [1e6 + 1e-9, 1e6]])),
              st.sampled_from([1e-9, 0.1, 1.75, 1e6]), st.sampled_from([0.0, 1.75, 1e6]), st.booleans()),
    st.builds(lambda g, tol, obs: {"kind": "goal", "goal": g, "goal_tolerance": tol, "obstacles": obs},
              st.tuples(floats, floats).map(list), st.sampled_from([1e-9, 0.5, 1e6]),
              st.lists(st.fixed_dictionaries({"x": floats, "y": floats, "r": st.sampled_from([1e-9, 0.5, 1e6])}),
                       max_size=3)),
)


def _deep(n: int, kind: str) -> bytes:
    return (b"[" * n + b"]" * n) if kind == "list" else (b'{"a":' * n + b"1" + b"}" * n)


def huge_payloads(model: type[Message]) -> st.SearchStrategy[bytes]:
    """Huge arrays in every list field of a message, deep nesting, and payloads over the size limit."""
    big = st.sampled_from([1_000, 50_000])
    out = [
        st.builds(_deep, st.sampled_from([64, 1000, 100_000]), st.sampled_from(["list", "dict"])),
        st.just(b" " * (MAX_PAYLOAD_BYTES + 1)),
    ]
    if model is State:
        out.append(big.map(lambda n: json.dumps({"x": 0, "y": 0, "theta": 0, "v": 0, "omega": 0,
                                                 "covariance": [0.0] * n}).encode()))
    if model is Task:
        out.append(big.map(lambda n: json.dumps({"kind": "lane", "centerline": [[0.0, 0.0]] * n}).encode()))
    if model is Plan:
        out.append(big.map(lambda n: json.dumps({"command": {"v_ref": 0, "omega_ref": 0}, "controls": [[0, 0]] * n,
                                                 "states": [[0.0] * 5] * n}).encode()))
    return st.one_of(*out)


def _encode_as(obj: Any, how: str) -> bytes:
    text_ = json.dumps(obj)
    if how == "utf-16":
        return text_.encode("utf-16")
    if how == "utf-32":
        return text_.encode("utf-32")
    if how == "bom":
        return b"\xef\xbb\xbf" + text_.encode()
    if how == "gzip":
        return gzip.compress(text_.encode(), mtime=0)
    if how == "latin-1":
        return (text_[:-1] + ', "s": "\xe9\xff"}').encode("latin-1") if text_.endswith("}") else text_.encode()
    return text_.encode()


def junk(model: type[Message]) -> st.SearchStrategy[bytes]:
    """Payloads that are not a valid message of `model`: bytes, broken JSON, other JSON, other text encodings."""
    shaped = model_dicts(model)
    json_values = st.recursive(
        st.one_of(st.none(), st.booleans(), floats, ints, text),
        lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(text, inner, max_size=4)),
        max_leaves=12,
    )
    return st.one_of(
        st.binary(max_size=64),
        st.just(b""),
        text.map(str.encode),
        shaped.map(lambda d: json.dumps(d).encode()[: max(1, len(json.dumps(d)) // 2)]),  # truncated
        json_values.map(lambda v: json.dumps(v).encode()),
        st.tuples(shaped, st.sampled_from(["utf-16", "utf-32", "bom", "gzip", "latin-1"])).map(
            lambda t: _encode_as(t[0], t[1])
        ),
        huge_payloads(model),
    )


def payloads(model: type[Message], extreme: st.SearchStrategy | None = None) -> st.SearchStrategy:
    """What the fuzz tests send on a key carrying `model`: junk bytes, or a dict from the model's fields, or a
    valid-but-extreme message (`extreme`, a strategy of dicts)."""
    options: list[st.SearchStrategy] = [junk(model), model_dicts(model)]
    if extreme is not None:
        options += [extreme, extreme]
    return st.one_of(*options)


def materialize(payload: bytes | dict) -> bytes:
    """The bytes to send: a dict's NOW stamps replaced by the current time, then JSON (NaN and Infinity as
    JavaScript writes them, which strict JSON parsers reject)."""
    if isinstance(payload, bytes):
        return payload

    def fill(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: (time.time_ns() if k == "stamp_ns" and x == NOW else fill(x)) for k, x in v.items()}
        if isinstance(v, list):
            return [fill(x) for x in v]
        return v

    return json.dumps(fill(payload)).encode()


__all__ = ["NOW", "Header", "extreme_tasks", "junk", "materialize", "model_dicts", "payloads", "valid_state"]
