"""The planner config's `critics:` section, derived from the registered critics.

Each entry is `name: {weight, enabled, tasks, <parameters>}`, every key optional (the critic's defaults):
`weight` finite and >= 0, `enabled` (false: weight 0), `tasks` the task kinds the critic runs in (a subset of those
it supports; default all of them), and the critic's own parameters (`base.Critic.params`). An unknown critic or key,
a bad weight or parameter, or a task kind the critic does not support is an error naming it and the valid choices.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from gpmppi.mppi.critics.registry import layout

__all__ = ["CRITIC_KEYS", "critic_settings", "critic_weights"]

CRITIC_KEYS = ("weight", "enabled", "tasks")


def critic_settings(raw: Mapping[str, Any] | None) -> dict[str, dict[str, Any]]:
    """Every registered critic's settings: `raw` (the config's section, possibly partial) checked and completed with
    the defaults; a ValueError names what was wrong."""
    critics = {c.name: c for c in layout().critics}
    raw = dict(raw or {})
    unknown = sorted(set(raw) - set(critics))
    if unknown:
        raise ValueError(f"critics: unknown critic {', '.join(map(repr, unknown))}; the critics are {list(critics)}")
    out: dict[str, dict[str, Any]] = {}
    for name, critic in critics.items():
        given = raw.get(name) or {}
        if not isinstance(given, Mapping):
            raise ValueError(f"critics.{name} must be a mapping of {list(CRITIC_KEYS) + list(critic.params)}, got "
                             f"{given!r}")
        valid = [*CRITIC_KEYS, *critic.params]
        bad = sorted(set(given) - set(valid))
        if bad:
            raise ValueError(f"critics.{name}: unknown parameter {', '.join(map(repr, bad))}; its parameters are "
                             f"{valid}")
        weight = given.get("weight", critic.weight)
        if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not math.isfinite(weight) or weight < 0:
            raise ValueError(f"critics.{name}.weight must be a finite number >= 0, got {weight!r}")
        enabled = given.get("enabled", True)
        if not isinstance(enabled, bool):
            raise ValueError(f"critics.{name}.enabled must be true or false, got {enabled!r}")
        tasks = given.get("tasks", list(critic.tasks))
        if isinstance(tasks, str) or not all(isinstance(t, str) for t in tasks):
            raise ValueError(f"critics.{name}.tasks must be a list of task kinds, got {tasks!r}")
        unsupported = [t for t in tasks if t not in critic.tasks]
        if unsupported:
            raise ValueError(f"critics.{name} is enabled for task kind {', '.join(map(repr, unsupported))}, which it "
                             f"does not support; it supports {list(critic.tasks)}")
        params = {p: spec.check(name, p, given.get(p, spec.default)) for p, spec in critic.params.items()}
        out[name] = {"weight": float(weight), "enabled": enabled, "tasks": list(tasks), **params}
    return out


def critic_weights(settings: Mapping[str, Mapping[str, Any]], task: str) -> dict[str, float]:
    """Each critic's weight in a task kind ('lane' or 'goal'): 0 where it is disabled or not run in that kind."""
    return {name: s["weight"] if s["enabled"] and task in s["tasks"] else 0.0 for name, s in settings.items()}
