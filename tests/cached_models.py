"""The models the tests plan and estimate with, made once per test process and handed out as copies.

`load_default_model()` decodes the shipped profile's file every call (its 57 MB grid table is most of it, ~0.1 CPU s a
call), and `synthetic_model(...)` solves its GPs and tabulates its grid every call (0.1-0.6 CPU s on 2 cores); the
tests called them ~80 and ~45 times. `shipped_model()` and `synthetic_model(...)` here hand each caller a deep copy
of one model made per arguments instead (~0.01 CPU s): the same arrays bit for bit, with the same flags (writeable,
contiguous: a numba kernel sees the same types), and no caller can change what another one gets, whatever it does to
its copy (tests/test_cached_models.py)."""

from __future__ import annotations

import copy
import functools

from gpmppi.gp.model_file import GPModel, load_default_model
from gpmppi.mppi import synthetic


@functools.cache
def _shipped() -> GPModel:
    return load_default_model()


@functools.cache
def _synthetic(terrains: tuple[str, ...], n_train: int, nodes: int, seed: int) -> GPModel:
    return synthetic.synthetic_model(terrains, n_train=n_train, nodes=nodes, seed=seed)


def shipped_model() -> GPModel:
    """What `gpmppi.gp.model_file.load_default_model()` returns: a model of its own, equal to a fresh load."""
    return copy.deepcopy(_shipped())


def synthetic_model(terrains: tuple[str, ...] = ("asphalt", "grass", "tile"), n_train: int = 120, nodes: int = 9,
                    seed: int = 0) -> GPModel:
    """What `gpmppi.mppi.synthetic.synthetic_model(...)` returns for these arguments: a model of its own, equal to a
    fresh one."""
    return copy.deepcopy(_synthetic(tuple(terrains), n_train, nodes, seed))
