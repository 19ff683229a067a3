"""A small most-recently-used store for geometry built once per task (lane lookups, goal fields)."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

T = TypeVar("T")


class Recent(Generic[T]):
    """Keeps the last `kept` values by key: planners of one process then share what a task needs built."""

    def __init__(self, kept: int = 8) -> None:
        self._items: OrderedDict[Hashable, T] = OrderedDict()
        self._kept = kept

    def get(self, key: Hashable, build: Callable[[], T]) -> T:
        found = self._items.get(key)
        if found is None:
            found = build()
            self._items[key] = found
            while len(self._items) > self._kept:
                self._items.popitem(last=False)
        else:
            self._items.move_to_end(key)
        return found
