"""gpmppi: chance-constrained GP-MPPI for skid-steer robots. Pure: arrays in, arrays out.

Two process-wide settings are made here, before any submodule imports numba:

- numba's on-disk cache (`cache=True`) is keyed on the defining file's timestamp only, so a
  kernel that inlines a helper from another file silently keeps the old helper after an
  update. The cache therefore lives in a folder named by a hash of this package's sources:
  any source change gives a fresh cache, and services still start warm between runs (also
  where numba was imported before this package, whose setting is then changed in place). numba
  writes that cache without a lock, so processes compiling at once could cross its entries;
  `numba_cache_lock` adds one.
- numba's OpenMP pool spin-waits between parallel regions by default; on a small shared
  machine the spinning threads steal the cores the kernels need (measured: a 2-thread kernel
  ran 2x slower than 1 thread). Passive waiting is chosen unless the user set a policy.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

__version__ = "0.1.0"


def _source_digest() -> str:
    h = hashlib.sha1()
    root = Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


if "NUMBA_CACHE_DIR" not in os.environ:
    _cache_root = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    os.environ["NUMBA_CACHE_DIR"] = str(_cache_root / "gpmppi" / "numba" / _source_digest())
    if "numba.core.config" in sys.modules:
        # numba was imported first (a script's `import numba` above `import gpmppi`, a test module sorted so) and
        # read its settings then: without this it caches next to the sources (`__pycache__`), keyed on each file's
        # own timestamp, and a kernel kept a helper from another file as it was before that file changed (plans
        # with the lazily collapsed table then differed from the whole collapse by an ulp)
        sys.modules["numba.core.config"].CACHE_DIR = os.environ["NUMBA_CACHE_DIR"]
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gpmppi.numba_cache_lock import install as _lock_numba_cache  # noqa: E402 - after the settings above

_lock_numba_cache()
