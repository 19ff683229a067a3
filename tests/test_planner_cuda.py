"""The CUDA backend under the CUDA simulator agrees with the CPU backend (same noise, same costs)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cuda_mode import ON_DEVICE, cuda_env

REPO = Path(__file__).resolve().parents[1]

SCRIPT = r"""
import json
import sys
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
for dyn in sys.argv[1:]:
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


CONFIGURATIONS = [["gp", "gp-coloured", "gp-limited"], ["gp-multilinear"], ["edd5", "unicycle"]]


@pytest.fixture(scope="module")
def sim_results(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """SCRIPT over the configurations, a process per group, all started at once (each compiles its own kernels:
    on a machine with more cores than two they compile side by side)."""
    env = cuda_env(PYTHONWARNINGS="ignore::RuntimeWarning")
    folder = tmp_path_factory.mktemp("cuda-vs-cpu")
    procs = []
    for i, group in enumerate(CONFIGURATIONS):
        with (folder / f"{i}.out").open("w") as out, (folder / f"{i}.err").open("w") as err:  # files: no pipe fills
            procs.append(subprocess.Popen([sys.executable, "-c", SCRIPT, *group], cwd=REPO, env=env, stdout=out,
                                          stderr=err, text=True))
    results: dict = {}
    try:
        for i, proc in enumerate(procs):
            proc.wait(timeout=600)
            assert proc.returncode == 0, (folder / f"{i}.err").read_text()[-3000:]
            results.update(json.loads((folder / f"{i}.out").read_text().strip().splitlines()[-1]))
    finally:
        for proc in procs:  # a failed group leaves no compiling process behind
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    return results


@pytest.mark.slow(seconds=8)  # twelve plans under numba's CUDA simulator
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
collapses = []
x = sc.start.copy()
for weights in (w, w.copy(), np.array([0.2, 0.3, 0.5])):
    r = p.plan(x, sc.task, weights)
    counts.append(dict(p.device.uploads))
    x = r.states[1]
    collapses.append(p.device.collapses)
src_uploads = p.device._versions[("model", "table_src")]
# a table marked lazily collapsed with no per-terrain rows to collapse it from is refused, by name
from gpmppi.mppi.cuda_backend import cuda_rollouts
broken = p.terrain.set_weights(w).args()._replace(table_src=np.zeros((1, 4), dtype=np.float32),
                                                  lazy=np.ones(1, dtype=np.int64))
try:
    cuda_rollouts(broken, None, None, None, None)
    refused = ""
except ValueError as exc:
    refused = str(exc)
n_arrays = sum(isinstance(a, np.ndarray) for a in p.terrain.set_weights(w).args())
print(json.dumps({"counts": counts, "model_arrays": n_arrays, "collapses": collapses, "src_uploads": src_uploads,
                  "refused": refused}))
"""


def test_cuda_backend_uploads_the_model_only_when_it_or_the_weights_change() -> None:
    env = cuda_env(PYTHONWARNINGS="ignore::RuntimeWarning")
    proc = subprocess.run([sys.executable, "-c", UPLOADS], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    first, second, moved = got["counts"]
    assert first["model"] == got["model_arrays"]  # the first plan uploads every model array
    assert second["model"] == first["model"]  # same model, same weights (a new but equal array): none again
    assert second["task"] == first["task"] + 1  # of the task only what is new each plan: the tightened bounds
    assert second["sampling"] > first["sampling"]  # the start state and the nominal sequence travel every plan
    # new weights: their collapse factors, the weights and the weighted slide coefficients; the per-terrain rows,
    # theta, EDD5 and the grid's shape stay on the device
    assert 0 < moved["model"] - second["model"] <= 3
    # the table is collapsed on the device from per-terrain rows uploaded once: once per weights, not per plan
    assert got["collapses"] == [1, 1, 2]
    assert got["src_uploads"] == 1
    assert "lazily collapsed" in got["refused"] and "table_src" in got["refused"]


AGREEMENT = r"""
import json
import sys
import numpy as np
from gpmppi.gp.model_file import load_default_model
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.mppi.synthetic import synthetic_model
from gpmppi.models.kinematic_unicycle import kinematic_step
from gpmppi.scenarios import circle_lane

samples, horizon, which = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
model = load_default_model() if which == "shipped" else synthetic_model(nodes=5, n_train=30)
sc = circle_lane()
planners = {name: Planner(PlannerConfig(backend=backend, samples=samples, horizon=horizon, sample_output=samples,
                                        seed=7, table_collapse=collapse), model)
            for name, backend, collapse in (("cpu", "cpu", "lazy"), ("cuda", "cuda", "lazy"),
                                            ("cuda_whole", "cuda", "whole"))}
x = sc.start.copy()
# the weights held for a second plan, then moved (the device collapses again)
weights = [np.array([0.6, 0.3, 0.1]), np.array([0.6, 0.3, 0.1]), np.array([0.2, 0.5, 0.3])]
out = {name: [] for name in planners}
for w in weights:
    results = {name: p.plan(x, sc.task, w) for name, p in planners.items()}
    for name, r in results.items():
        out[name].append({"costs": r.sample_costs.tolist(), "controls": r.controls.tolist(), "cost": r.cost})
    x = kinematic_step(x, results["cpu"].control, 0.1)
out["collapses"] = planners["cuda"].device.collapses
print(json.dumps(out))
"""


@pytest.mark.slow(seconds=6)  # plans under numba's CUDA simulator, in a process of its own
def test_cpu_and_cuda_plans_agree() -> None:
    """CPU and CUDA score the same samples alike (to float32 rounding) and make the same update. On a real GPU
    (tests/cuda_mode.py) at the deployed size, S=1024, N=40, with the shipped model's grid table; under the simulator
    at a size it runs in seconds (S=64, N=10, a small synthetic model)."""
    size = ("1024", "40", "shipped") if ON_DEVICE else ("64", "10", "synthetic")
    proc = subprocess.run([sys.executable, "-c", AGREEMENT, *size], cwd=REPO,
                          env=cuda_env(PYTHONWARNINGS="ignore::RuntimeWarning"), capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got["collapses"] == 2  # once per weights, on the device
    for step, (cpu, gpu, whole) in enumerate(zip(got["cpu"], got["cuda"], got["cuda_whole"], strict=True)):
        costs = np.array(cpu["costs"])
        assert len(costs) == int(size[0]) and np.isfinite(costs).mean() > 0.9, step
        # the device's own table collapse gives the table the host's whole collapse gives (to the float32 table's
        # last bit: NVVM fuses the collapse's multiply-adds)
        np.testing.assert_allclose(gpu["costs"], whole["costs"], rtol=1e-6, atol=1e-9, err_msg=f"step {step}")
        np.testing.assert_allclose(gpu["costs"], costs, rtol=1e-5, atol=1e-6, err_msg=f"step {step}")
        np.testing.assert_allclose(gpu["controls"], cpu["controls"], rtol=0, atol=1e-4, err_msg=f"step {step}")
        assert gpu["cost"] == pytest.approx(cpu["cost"], rel=1e-5)
