"""The CUDA device functions agree with the CPU predictors (numba CUDA simulator, in a subprocess)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

from cuda_mode import cuda_env

REPO = Path(__file__).resolve().parents[1]

SCRIPT = textwrap.dedent(
    """
    import numpy as np
    import os
    from numba import config
    # the simulator unless the tests run on a real device (tests/cuda_mode.py)
    assert bool(config.ENABLE_CUDASIM) == (os.environ.get("GPMPPI_CUDA_DEVICE") != "1")
    from gpmppi.gp.cuda_kernels import cuda_predict
    from gpmppi.gp.exact import ExactPredictor
    from gpmppi.gp.grid import GridPredictor, build_grid
    from gpmppi.gp.model_file import GPModel, task_names
    from gpmppi.gp.train import Hyperparameters, factorize

    rng = np.random.default_rng(3)
    n, terrains = 12, ["a", "b"]
    x = rng.uniform([0, -1, 0, -1], [2, 1, 2, 1], (n, 4))
    hp = Hyperparameters(rng.uniform(0.5, 2.0, (4, 4)), rng.uniform(0.01, 0.1, 4), np.full(4, 1e-3))
    y = rng.normal(0, 0.1, (4, n))
    chol, alpha = factorize(x, y, hp)
    model = GPModel(terrains, task_names(terrains), np.ones(6), {t: np.ones(5) for t in terrains},
                    np.array([0, -1, 0, -1.0]), np.array([2, 1, 2, 1.0]), x, hp.lengthscale, hp.outputscale,
                    hp.noise, chol, alpha)
    model.set_grid(build_grid(model, 5))
    q = rng.uniform([-0.2, -1.2, -0.2, -1.2], [2.2, 1.2, 2.2, 1.2], (40, 4))  # includes clamped points
    cm, cv = cuda_predict(model, q, "exact", threads=16)
    em, ev = ExactPredictor(model).predict(q)
    np.testing.assert_allclose(cm, em, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(cv, ev, rtol=1e-10, atol=1e-14)
    assert np.all(ev > 0) and np.std(em) > 1e-3   # a non-trivial comparison
    gm, gv = cuda_predict(model, q, "grid", threads=16)
    hm, hv = GridPredictor(model).predict(q)
    np.testing.assert_allclose(gm, hm, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(gv, hv, rtol=1e-10, atol=1e-14)
    print("CUDASIM-OK")
    """
)


def test_cuda_device_functions_match_cpu() -> None:
    env = cuda_env()
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "CUDASIM-OK" in proc.stdout
