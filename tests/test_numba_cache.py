"""numba's kernel cache: in the folder named by the sources' hash even where numba was imported first, and written
under a lock (`gpmppi.numba_cache_lock`), in real child processes."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from gpmppi.numba_cache_lock import index_lock

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="flock is POSIX")

_CHILD = textwrap.dedent(
    """
    import sys
    import gpmppi  # installs the lock before numba is imported
    sys.path.insert(0, sys.argv[1])
    import cached_twice
    cache_file = cached_twice.add_one._cache._cache_file
    print(cache_file._index_path, flush=True)
    sys.stdin.readline()  # the parent holds the lock now
    assert cached_twice.add_one(1.5) == 2.5
    print("compiled", flush=True)
    """
)


def _index_entries(index_path: str) -> dict:
    with open(index_path, "rb") as f:
        pickle.load(f)  # numba's version
        _, overloads = pickle.loads(f.read())
    return overloads


def test_a_process_waits_for_the_cache_lock_before_writing_the_index(tmp_path: Path) -> None:
    (tmp_path / "cached_twice.py").write_text(
        "from numba import njit\n\n\n@njit(cache=True)\ndef add_one(x):\n    return x + 1\n"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    child = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(tmp_path)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env
    )
    try:
        index_path = child.stdout.readline().strip()
        assert index_path.endswith(".nbi"), index_path
        with index_lock(index_path, exclusive=True):
            child.stdin.write("go\n")
            child.stdin.flush()
            time.sleep(2.0)  # compiling add_one takes well under this: unlocked, the child would have written
            assert child.poll() is None, "the child finished while the lock was held"
            assert not os.path.exists(index_path), "the index was written while the lock was held"
        assert child.stdout.readline().strip() == "compiled"
        assert child.wait(timeout=60) == 0
    finally:
        if child.poll() is None:
            child.kill()
    entries = _index_entries(index_path)
    assert len(entries) == 1
    ((key, data_name),) = entries.items()
    assert str(key[0]) == "(float64,)" and (Path(index_path).parent / data_name).exists()


_NUMBA_FIRST = textwrap.dedent(
    """
    import numba  # before gpmppi, as a script or a test module sorted by isort may
    import gpmppi
    from gpmppi.mppi.gp_table import collapse_rows
    print(collapse_rows._cache._cache_path)
    """
)


def test_the_kernel_cache_is_the_hashed_folder_even_where_numba_was_imported_first(tmp_path: Path) -> None:
    """Imported first, numba would cache next to the sources, keyed on each file's own timestamp: a kernel then kept
    a helper from another file as it was before that file changed (seen: lazily collapsed slabs an ulp off)."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    out = subprocess.run([sys.executable, "-c", _NUMBA_FIRST], env=env, capture_output=True, text=True, check=True)
    assert Path(out.stdout.strip()).is_relative_to(tmp_path / "gpmppi" / "numba"), out.stdout


def test_a_cache_folder_that_cannot_take_a_lock_file_is_read_unlocked(tmp_path: Path) -> None:
    """numba may load a cache where no lock file can be made (a read-only install): no lock then, and no error."""
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    index = blocker / "cache" / "f-1.py311.nbi"  # under a file: no folder, so no lock file, even for root
    with index_lock(str(index), exclusive=False):
        pass
    assert not Path(str(index) + ".lock").exists()
