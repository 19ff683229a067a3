"""numba's on-disk kernel cache, made safe for several processes writing it at once.

numba keeps one index per cached function (signature -> data file) and writes it without a lock: a process
reads the index, picks the first free data-file number, writes the index, then the data. Two processes that
compile different signatures of one function at the same time can both pick number 1; the index then names
one signature while the data file holds the other's machine code, and every later process loads the wrong
code for that signature (numba/numba#10128 reports a crash from the same kind of race). The stack meets it:
the services, the evaluation's workers and the test workers compile into one cache folder.

`install()` wraps numba's index-and-data reads and writes in a per-function file lock (`flock`): a writer holds
it exclusively from reading the index to writing the data, a reader shared from reading the index to reading
the data. It patches `numba.core.caching` when that module is first imported (or at once if it already is),
so `import gpmppi` does not import numba in processes that never compile (recorder, egress, viewer).
"""

from __future__ import annotations

import contextlib
import importlib.abc
import importlib.util
import os
import sys
from collections.abc import Iterator
from types import ModuleType

try:
    import fcntl
except ImportError:  # not a POSIX system: numba's own (unlocked) behaviour
    fcntl = None  # type: ignore[assignment]

_MODULE = "numba.core.caching"


def lock_path(index_path: str) -> str:
    """The lock file beside a numba cache index (`*.nbi`)."""
    return index_path + ".lock"


@contextlib.contextmanager
def index_lock(index_path: str, exclusive: bool) -> Iterator[None]:
    """Hold the lock of the cache index at `index_path`: exclusive to write it, shared to read it."""
    if fcntl is None:
        yield
        return
    try:
        os.makedirs(os.path.dirname(index_path), exist_ok=True)
        fd = os.open(lock_path(index_path), os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:  # a folder numba can read but this process cannot write: numba's own (unlocked) behaviour
        yield
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def patch(caching: ModuleType) -> None:
    """Wrap `IndexDataCacheFile.save`, `.load` and `.flush` of the module `numba.core.caching` in `index_lock`."""
    cls = caching.IndexDataCacheFile
    if getattr(cls, "_gpmppi_locked", False):
        return
    save, load, flush = cls.save, cls.load, cls.flush

    def locked_save(self, key, data):  # noqa: ANN001, ANN202 - numba's signature
        with index_lock(self._index_path, exclusive=True):
            return save(self, key, data)

    def locked_load(self, key):  # noqa: ANN001, ANN202
        with index_lock(self._index_path, exclusive=False):
            return load(self, key)

    def locked_flush(self):  # noqa: ANN001, ANN202
        with index_lock(self._index_path, exclusive=True):
            return flush(self)

    cls.save, cls.load, cls.flush = locked_save, locked_load, locked_flush
    cls._gpmppi_locked = True


class _PatchOnImport(importlib.abc.MetaPathFinder):
    """Finds `numba.core.caching` through the other finders and patches it once it has run."""

    def find_spec(self, name: str, path, target=None):  # noqa: ANN001, ANN201 - the finder protocol
        if name != _MODULE:
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            return spec
        run = spec.loader.exec_module

        def exec_module(module: ModuleType) -> None:
            run(module)
            patch(module)

        spec.loader.exec_module = exec_module  # type: ignore[method-assign]
        return spec


def install() -> None:
    """Lock numba's cache index from now on in this process (idempotent)."""
    if _MODULE in sys.modules:
        patch(sys.modules[_MODULE])
    elif not any(isinstance(f, _PatchOnImport) for f in sys.meta_path):
        sys.meta_path.insert(0, _PatchOnImport())
