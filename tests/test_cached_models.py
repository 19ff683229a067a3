"""tests/cached_models.py hands out what a fresh load or build gives, bit for bit, and copies no test can share."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import numpy as np
from cached_models import shipped_model, synthetic_model

from gpmppi.gp.model_file import GPModel, load_default_model
from gpmppi.mppi import synthetic


def _leaves(obj: object, path: str = "model") -> Iterator[tuple[str, object]]:
    """(path, value) of every array and plain value inside a model: dataclass fields, dicts, sequences, attributes."""
    if isinstance(obj, np.ndarray):
        yield path, obj
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            yield from _leaves(getattr(obj, f.name), f"{path}.{f.name}")
    elif isinstance(obj, dict):
        for key, value in obj.items():
            yield from _leaves(value, f"{path}[{key!r}]")
    elif isinstance(obj, list | tuple):
        for k, value in enumerate(obj):
            yield from _leaves(value, f"{path}[{k}]")
    elif hasattr(obj, "__dict__"):
        for key, value in vars(obj).items():
            yield from _leaves(value, f"{path}.{key}")
    else:
        yield path, obj


def _assert_same(ours: GPModel, fresh: GPModel) -> None:
    a, b = list(_leaves(ours)), list(_leaves(fresh))
    assert [p for p, _ in a] == [p for p, _ in b]
    assert any(isinstance(v, np.ndarray) and v.size > 1000 for _, v in a)  # the grid table is among them
    for (path, x), (_, y) in zip(a, b, strict=True):
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray) and x.dtype == y.dtype and x.shape == y.shape, path
            assert x.tobytes() == y.tobytes(), path  # bit for bit (NaN included)
            assert (x.flags.writeable, x.flags.c_contiguous, x.flags.aligned) == (
                y.flags.writeable, y.flags.c_contiguous, y.flags.aligned), path
        else:
            assert type(x) is type(y) and x == y, path


def test_the_shipped_model_is_a_fresh_load_bit_for_bit() -> None:
    _assert_same(shipped_model(), load_default_model())


def test_a_synthetic_model_is_a_fresh_build_bit_for_bit() -> None:
    _assert_same(synthetic_model(nodes=4, n_train=20), synthetic.synthetic_model(nodes=4, n_train=20))
    _assert_same(synthetic_model(terrains=("gravel", "mulch"), nodes=4, n_train=20, seed=3),
                 synthetic.synthetic_model(("gravel", "mulch"), nodes=4, n_train=20, seed=3))


def test_what_one_caller_does_to_its_model_no_other_caller_sees() -> None:
    for make in (shipped_model, lambda: synthetic_model(nodes=4, n_train=20)):
        first = make()
        untouched = list(_leaves(make()))
        first.grid().table[...] = 0.0
        first.alpha += 1.0
        first.terrains.append("ice")
        first.edd5[first.terrains[0]][:] = 0.0
        first.calibration = None
        second = make()
        assert second is not first and second.grid().table is not first.grid().table
        for (path, x), (_, y) in zip(untouched, _leaves(second), strict=True):
            assert (x.tobytes() == y.tobytes()) if isinstance(x, np.ndarray) else x == y, path
