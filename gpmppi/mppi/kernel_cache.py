"""Whether a planner configuration's numba kernels are in the on-disk cache, so a service can say that it has to
compile before it does (about 20 s on a small machine, once) instead of sitting silent.

Which kernels (and which type signatures) a configuration uses is only known once it has planned: after its
first warm-up the service records them in a small manifest next to numba's own cache files
(`$NUMBA_CACHE_DIR/gpmppi-kernels/<label>.json`). A configuration is cached when that manifest exists and numba's
index for each kernel listed holds the signature for this machine (numba's own lookup key: the signature and the
code generator's magic tuple; its index is empty when stale). An empty cache folder has no manifest: not cached.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import marshal
import os
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from numba.core import config as numba_config
from numba.core.dispatcher import Dispatcher

# a planner's first cycle on an empty cache (the delay prediction, the plan, the per-critic split; the rollout kernel
# compiled in a second process, `compile_ahead`): `gpmppi warm`'s "planner on circle" took 20-25 s wall on an idle
# 2-core machine (2026-12-04); used until this machine has measured its own
REFERENCE_COMPILE_S = 22.0
_MANIFEST_DIR = "gpmppi-kernels"

Counts = dict[str, tuple[dict[str, int], dict[str, int]]]  # kernel -> (loads by signature, compiles by signature)


@dataclass
class KernelUse:
    """What a stretch of code did with the cached kernels: per kernel, the signatures loaded and compiled."""

    loaded: dict[str, list[str]] = field(default_factory=dict)
    compiled: dict[str, list[str]] = field(default_factory=dict)


def _disk_cached() -> Iterator[object]:
    """Every disk-cached numba dispatcher (CPU and CUDA) of gpmppi's imported modules."""
    seen: set[int] = set()
    for module_name, module in list(sys.modules.items()):
        if not (module_name == "gpmppi" or module_name.startswith("gpmppi.")) or module is None:
            continue
        for value in list(vars(module).values()):
            if (id(value) not in seen and hasattr(value, "enable_caching")
                    and hasattr(getattr(value, "_cache", None), "_cache_file")):
                seen.add(id(value))
                yield value


def _kernels() -> Iterator[tuple[str, Dispatcher]]:
    """Every disk-cached numba kernel (CPU) of gpmppi's imported modules, by `module:qualname`."""
    for value in _disk_cached():
        if isinstance(value, Dispatcher):
            yield f"{value.py_func.__module__}:{value.py_func.__qualname__}", value


def key_cache_to_outside_critics(functions: list[Callable]) -> Path | None:
    """Give this process a kernel cache of its own when a critic's code (`functions`: the registered critics' terms)
    lies outside the gpmppi package, and return that folder (None: every critic is the package's own).

    The cache's folder is named by a hash of the package's sources (`gpmppi/__init__.py`): a critic module under
    `gpmppi/mppi/critics/` changes it, one registered from elsewhere does not, and the rollout kernel cached before
    would be loaded without that critic (numba keys a kernel on its own file only). So the folder gains a hash of
    the outside modules' sources (the same plug-ins share it; a changed plug-in gets a new one), and every
    disk-cached dispatcher of gpmppi imported so far is pointed at it (numba's `enable_caching` reads the setting
    anew); modules imported later read it themselves. Called once, when the critics' layout is built, before any
    kernel that calls a critic is compiled or loaded."""
    python = [getattr(f, "py_func", f) for f in functions]
    own = {name for name in sys.modules if name == "gpmppi" or name.startswith("gpmppi.")}
    outside = sorted({f.__module__ for f in python} - own)
    if not outside:
        return None
    digest = hashlib.sha1()
    sourceless = set()
    for name in outside:  # the modules' sources (not their paths: the same plug-in elsewhere shares the folder)
        source = getattr(sys.modules.get(name), "__file__", None)
        digest.update(name.encode() + b"\0" + (Path(source).read_bytes() if source else b""))
        if not source:
            sourceless.add(name)
    for f in python:  # a module without a file (a `python -c` script): the functions' code
        if f.__module__ in sourceless:
            digest.update(marshal.dumps(f.__code__))
    suffix = f"-critics-{digest.hexdigest()[:16]}"
    folder = cache_folder()
    if not folder.name.endswith(suffix):  # a child process (compile ahead) inherits the keyed folder already
        folder = folder.with_name(folder.name + suffix)
    os.environ["NUMBA_CACHE_DIR"] = numba_config.CACHE_DIR = str(folder)
    for dispatcher in _disk_cached():
        dispatcher.enable_caching()  # type: ignore[attr-defined]
    return folder


def cache_counts() -> Counts:
    """A snapshot of numba's cache loads and compiles so far in this process, for `kernels_used`."""
    return {name: ({str(s): n for s, n in d._cache_hits.items()}, {str(s): n for s, n in d._cache_misses.items()})
            for name, d in _kernels()}


def kernels_used(before: Counts, after: Counts) -> KernelUse:
    """The kernels loaded from the cache and compiled between two `cache_counts` snapshots."""
    use = KernelUse()
    for name, (hits, misses) in after.items():
        old_hits, old_misses = before.get(name, ({}, {}))
        for into, new, old in ((use.loaded, hits, old_hits), (use.compiled, misses, old_misses)):
            sigs = [s for s, n in new.items() if n > old.get(s, 0)]
            if sigs:
                into[name] = sorted(sigs)
    return use


def cache_folder() -> Path:
    """numba's on-disk cache folder in this process."""
    return Path(numba_config.CACHE_DIR or os.environ.get("NUMBA_CACHE_DIR", ""))


def _manifest(label: str) -> Path:
    return cache_folder() / _MANIFEST_DIR / f"{label.replace('/', '-').replace(' ', '_')}.json"


def record(label: str, use: KernelUse, compile_s: float | None) -> None:
    """Remember which kernels configuration `label` used (and, if it compiled, how long that took)."""
    path = _manifest(label)
    kernels: dict[str, list[str]] = {}
    for part in (use.loaded, use.compiled):
        for name, sigs in part.items():
            kernels[name] = sorted({*kernels.get(name, []), *sigs})
    if not kernels:
        return
    previous = _read(path)
    # a configuration warmed on several tasks (a lane, then a goal) lists the kernels of each
    old = previous.get("kernels")
    if isinstance(old, dict):
        for name, sigs in old.items():
            if isinstance(sigs, list):
                kernels[name] = sorted({*kernels.get(name, []), *map(str, sigs)})
    # the estimate is the compile that compiled the most kernels (a whole cold compile), not the last one: a start
    # that compiled one missing kernel in a second would otherwise announce the next cold compile as "about 1 s"
    best_s, best_n = previous.get("compile_s"), previous.get("compiled_kernels")
    measured = isinstance(best_s, int | float) and isinstance(best_n, int)
    if compile_s is not None and (not measured or len(use.compiled) >= best_n):
        best_s, best_n = compile_s, len(use.compiled)
    entry = {"kernels": kernels, "compile_s": best_s, "compiled_kernels": best_n if isinstance(best_n, int) else 0}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(entry, indent=1))
    tmp.replace(path)  # atomic: two services starting at once each write a whole file


def _read(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _lookup(name: str) -> Dispatcher | None:
    module_name, _, qualname = name.partition(":")
    try:
        value: object = importlib.import_module(module_name)
        for part in qualname.split("."):
            value = getattr(value, part)
    except (ImportError, AttributeError):
        return None
    return value if isinstance(value, Dispatcher) else None


def _in_index(dispatcher: Dispatcher, sig: str) -> bool:
    try:
        index = dispatcher._cache._cache_file._load_index()
        magic = dispatcher.targetctx.codegen().magic_tuple()
    except Exception:  # numba's private cache layout changed: say not cached rather than guess
        return False
    return any(str(key[0]) == sig and key[1] == magic for key in index)


def is_cached(label: str) -> bool:
    """Whether configuration `label` planned before with this cache and every kernel it used is still there."""
    kernels = _read(_manifest(label)).get("kernels")
    if not isinstance(kernels, dict) or not kernels:
        return False
    for name, sigs in kernels.items():
        dispatcher = _lookup(name)
        if dispatcher is None or not all(_in_index(dispatcher, s) for s in sigs):
            return False
    return True


def compile_estimate_s(label: str) -> tuple[float, str]:
    """About how long a cold compile of `label` takes, and where the number comes from."""
    measured = _read(_manifest(label)).get("compile_s")
    if isinstance(measured, int | float) and measured > 0:
        return float(measured), "as measured when this cache was last filled"
    return REFERENCE_COMPILE_S, "measured on 2 cores"


def planner_label(dynamics: str, gp_mode: str, backend: str) -> str:
    """The name a planner configuration's kernels are cached and announced under, e.g. 'gp/grid on cpu'."""
    label = f"{dynamics}/{gp_mode}" if dynamics == "gp" else dynamics
    return f"{label} on {backend}"


def warm_up(label: str, run: Callable[[], object], log: Callable[[str], None]) -> KernelUse:
    """Run `run` (one plan of configuration `label`), first saying so when its kernels are not cached (they are
    then compiled: seconds to a minute on a small machine, once per configuration and source version), afterwards
    how long the compile took; and record the kernels it used, so that the next start knows them cached.

    The planner service and `gpmppi warm` both warm up through here, so a cache filled by one is found by the other.
    """
    if not is_cached(label):
        estimate, source = compile_estimate_s(label)
        log(f"compiling planner kernels for {label} (not cached yet in {cache_folder()}; about {estimate:.0f} s, "
            f"{source}; once)")
    before = cache_counts()
    t = time.monotonic()
    run()
    seconds = time.monotonic() - t
    use = kernels_used(before, cache_counts())
    if use.compiled:
        log(f"compiled planner kernels for {label} in {seconds:.1f} s ({len(use.compiled)} kernels)")
    record(label, use, seconds if use.compiled else None)
    return use
