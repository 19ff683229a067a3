"""The suite's processes run one BLAS thread (tests/conftest.py): the test process itself, whose numpy was loaded
before conftest.py, and the processes it starts, which read it from the environment."""

from __future__ import annotations

import json
import subprocess
import sys

SCRIPT = """
import json
import numpy, scipy.linalg
from threadpoolctl import threadpool_info
print(json.dumps([info["num_threads"] for info in threadpool_info() if info["user_api"] == "blas"]))
"""


def test_the_test_process_and_the_processes_it_starts_run_one_blas_thread() -> None:
    import scipy.linalg  # noqa: F401 - scipy's own OpenBLAS, loaded after conftest.py
    from threadpoolctl import threadpool_info

    here = [info["num_threads"] for info in threadpool_info() if info["user_api"] == "blas"]
    child = json.loads(subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, check=True,
                                      timeout=120).stdout)
    assert len(here) >= 2 and set(here) == {1}, here  # numpy's and scipy's
    assert len(child) >= 2 and set(child) == {1}, child
