"""Where the CUDA tests run their kernels: numba's CUDA simulator (the default, on any machine) or a real GPU.

`GPMPPI_CUDA_DEVICE=1` runs the same tests on the GPU numba finds (the simulator left off), and the
agreement test at the deployed size (S=1024, N=40, the shipped model) rather than the simulator's small one.
"""

from __future__ import annotations

import os

ON_DEVICE = os.environ.get("GPMPPI_CUDA_DEVICE") == "1"


def cuda_env(**extra: str) -> dict[str, str]:
    """The environment of a child process that runs CUDA kernels: on the simulator unless on a real device."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_ENABLE_CUDASIM"}
    if not ON_DEVICE:
        env["NUMBA_ENABLE_CUDASIM"] = "1"
    env.update(extra)
    return env
