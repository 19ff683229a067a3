"""The CUDA kernels compile for a real GPU (NVVM to PTX), not only under the simulator.

The simulator runs the kernels as plain Python, so it cannot show that numba's CUDA target accepts
them (it does not, for example, compile float `min`/`max` or `np.sqrt`). Here the rollout kernel and
the GP kernels are compiled to PTX for compute capability 8.0 with the NVVM library that ships with
numba's CUDA toolchain; no GPU is needed (the device query numba makes for device functions is
answered with that compute capability).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

SCRIPT = r"""
import types
import numpy as np
from numba import cuda, typeof
import numba.cuda.dispatcher as cuda_dispatcher

cuda_dispatcher.get_current_device = lambda: types.SimpleNamespace(compute_capability=(8, 0))
from gpmppi.gp import cuda_kernels
from gpmppi.mppi import cuda_backend
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.mppi.synthetic import synthetic_model
from gpmppi.scenarios import circle_lane, paper_obstacle_scene

captured = []
cuda_backend.cuda_rollouts = lambda *bundles, device=None: captured.append(bundles)
model = synthetic_model(nodes=4, n_train=20)
for scenario in (circle_lane(), paper_obstacle_scene()):
    planner = Planner(PlannerConfig(backend="cpu", samples=8, horizon=4), model)
    planner.backend = "cuda"  # the rollouts go to the captured call above
    planner.plan(scenario.start, scenario.task, np.array([0.5, 0.3, 0.2]))
for bundles in captured:  # the five bundles' tuples, as the kernel takes them
    ptx, _ = cuda.compile_ptx(cuda_backend._rollout_kernel.py_func, tuple(typeof(b) for b in bundles), cc=(8, 0))
    assert ".entry" in ptx
x = np.zeros((3, 4))
mean = np.zeros((3, 6))
ptx, _ = cuda.compile_ptx(cuda_kernels._grid_kernel.py_func, tuple(typeof(v) for v in (
    x, np.zeros((3, 3, 3, 3, 12)), np.zeros(4), np.zeros(4), np.zeros((3, 12)))), cc=(8, 0))
assert ".entry" in ptx
ptx, _ = cuda.compile_ptx(cuda_kernels._exact_kernel.py_func, tuple(typeof(v) for v in (
    x, np.zeros((6, 5, 4)), np.zeros((6, 4)), np.zeros(6), np.zeros((6, 5)), np.zeros((6, 5, 5)), np.zeros((3, 5)),
    mean, mean)), cc=(8, 0))
assert ".entry" in ptx
ptx, _ = cuda.compile_ptx(cuda_backend._collapse_kernel.py_func, tuple(typeof(v) for v in (
    np.zeros((3, 12), dtype=np.float32), np.zeros(16), np.zeros((3, 4), dtype=np.float32))), cc=(8, 0))
assert ".entry" in ptx
print("compiled", len(captured) + 3)
"""


def _nvvm_available() -> bool:
    try:
        from numba.cuda.cudadrv import nvvm

        nvvm.NVVM()
        return True
    except Exception:  # no CUDA toolkit's NVVM on this machine
        return False


@pytest.mark.slow(seconds=25)  # the rollout kernel compiled to PTX twice (lane, goal) and the GP kernels once
@pytest.mark.skipif(not _nvvm_available(), reason="numba finds no NVVM library to compile CUDA to PTX")
def test_rollout_and_gp_kernels_compile_to_ptx() -> None:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_ENABLE_CUDASIM"}
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert proc.stdout.strip().endswith("compiled 5")
