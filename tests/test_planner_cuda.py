"""The CUDA backend under the CUDA simulator agrees with the CPU backend (same noise, same costs)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]

SCRIPT = r"""
import json
import numpy as np
from numba import cuda
from gpmppi.mppi.synthetic import synthetic_model
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.scenarios import circle_lane, paper_obstacle_scene
from gpmppi.models.kinematic_unicycle import kinematic_step

assert cuda.is_available()
model = synthetic_model(nodes=5, n_train=30)
w = np.array([0.5, 0.3, 0.2])
out = {}
for dyn in ["gp", "gp-multilinear", "gp-coloured", "gp-limited", "edd5", "unicycle"]:
    for sc in [circle_lane(), paper_obstacle_scene()]:
        runs = {}
        for backend in ["cpu", "cuda"]:
            interp = "multilinear" if dyn.endswith("multilinear") else "simplex"
            sampling = "coloured" if dyn.endswith("coloured") else "white"
            p = Planner(PlannerConfig(dynamics=dyn.split("-")[0], backend=backend, samples=16, horizon=5,
                                      sample_output=4, seed=3, grid_interpolation=interp, sampling=sampling,
                                      noise_correlation_time=0.3,
                                      accel_limits=(2.5, 3.2) if dyn.endswith("limited") else None), model)
            assert p.backend == backend
            x = sc.start.copy()
            res = []
            for _ in range(2):
                r = p.plan(x, sc.task, w)
                res.append({"costs": r.sample_costs.tolist(), "controls": r.controls.tolist(),
                            "xy": r.sample_states.tolist(), "cost": r.cost})
                x = kinematic_step(x, r.control, 0.1)
            runs[backend] = res
        auto = Planner(PlannerConfig(dynamics=dyn.split("-")[0], samples=16, horizon=5), model)
        runs["auto_backend"] = auto.backend
        out[f"{dyn}/{type(sc.task).__name__}"] = runs
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def sim_results() -> dict:
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1", PYTHONWARNINGS="ignore::RuntimeWarning")
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_cuda_simulator_matches_cpu_backend(sim_results: dict) -> None:
    assert len(sim_results) == 12
    for case, runs in sim_results.items():
        assert runs["auto_backend"] == "cuda", case  # auto picks CUDA when numba sees a device
        for cpu, gpu in zip(runs["cpu"], runs["cuda"], strict=True):
            # single- vs double-precision transcendentals in the simulator: agreement to ~1e-7
            np.testing.assert_allclose(gpu["costs"], cpu["costs"], rtol=1e-6, atol=1e-6, err_msg=case)
            np.testing.assert_allclose(gpu["controls"], cpu["controls"], rtol=0, atol=1e-5, err_msg=case)
            np.testing.assert_allclose(gpu["xy"], cpu["xy"], rtol=0, atol=1e-6, err_msg=case)
            assert np.isfinite(gpu["cost"])


UPLOADS = r"""
import json
import numpy as np
from gpmppi.mppi.synthetic import synthetic_model
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.scenarios import circle_lane

model = synthetic_model(nodes=5, n_train=30)
sc = circle_lane()
p = Planner(PlannerConfig(backend="cuda", samples=16, horizon=5, sample_output=4, seed=3), model)
w = np.array([0.5, 0.3, 0.2])
counts = []
x = sc.start.copy()
for weights in (w, w.copy(), np.array([0.2, 0.3, 0.5])):
    r = p.plan(x, sc.task, weights)
    counts.append(dict(p.device.uploads))
    x = r.states[1]
n_arrays = sum(isinstance(a, np.ndarray) for a in p._terrain_setup(w)[0].args())
print(json.dumps({"counts": counts, "model_arrays": n_arrays}))
"""


def test_cuda_backend_uploads_the_model_only_when_it_or_the_weights_change() -> None:
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1", PYTHONWARNINGS="ignore::RuntimeWarning")
    proc = subprocess.run([sys.executable, "-c", UPLOADS], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    first, second, moved = got["counts"]
    assert first["model"] == got["model_arrays"]  # the first plan uploads every model array
    assert second["model"] == first["model"]  # same model, same weights (a new but equal array): none again
    assert second["task"] == first["task"] + 1  # of the task only what is new each plan: the tightened bounds
    assert second["sampling"] > first["sampling"]  # the start state and the nominal sequence travel every plan
    # new weights: a new collapsed table, the weights and the weighted slide coefficients; theta, EDD5 and the
    # grid's shape stay on the device
    assert 0 < moved["model"] - second["model"] < got["model_arrays"]
