"""Critics as plug-ins: the config section `critics:` and its errors, and new critics added in one module and one
registration line each, counted by the CPU kernel, the CUDA kernel (simulator) and the per-critic split: a stateless
one, and a stateful one that carries a value from step to step (`critics.base.StepState`)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from cuda_mode import cuda_env

from gpmppi.mppi import kernel_cache
from gpmppi.mppi.bundles import CRITICS
from gpmppi.mppi.config import PlannerConfig
from gpmppi.mppi.critics.registry import layout

REPO = Path(__file__).resolve().parents[1]


def test_the_config_section_defaults_to_each_critic_module() -> None:
    c = PlannerConfig()
    assert list(c.critics) == list(CRITICS) == [critic.name for critic in layout().critics]
    assert c.critics["deviation"] == {"weight": 300.0, "enabled": True, "tasks": ["lane"]}
    assert c.critics["lane_exit"]["discount"] == 0.9 and c.critics["speed"]["along_lane"] is True
    assert c.critics["variance"]["tasks"] == ["lane", "goal"]


def test_disabled_or_restricted_critics_weigh_nothing_there() -> None:
    c = PlannerConfig(critics={"deviation": {"enabled": False}, "variance": {"tasks": ["goal"], "weight": 3}})
    lane, goal = c.critic_weights("lane"), c.critic_weights("goal")
    assert lane["deviation"] == 0.0 and lane["variance"] == 0.0 and goal["variance"] == 3.0
    assert lane["speed"] == 2.0 and goal["speed"] == 0.0 and goal["terminal"] == 10.0 and lane["terminal"] == 0.0
    bundle = c.cost_bundle("lane")
    assert bundle.params["lane_exit"] == {"discount": 0.9} and bundle.goal_geodesic


@pytest.mark.parametrize(("critics", "words"), [
    ({"slippage": {}}, r"unknown critic 'slippage'; the critics are \['variance', 'deviation'"),
    ({"speed": {"along": True}}, r"critics\.speed: unknown parameter 'along'; its parameters are \['weight', "
                                 r"'enabled', 'tasks', 'along_lane'\]"),
    ({"slip": {"weight": -1.0}}, r"critics\.slip\.weight must be a finite number >= 0, got -1\.0"),
    ({"goal": {"weight": float("nan")}}, r"critics\.goal\.weight must be a finite number >= 0, got nan"),
    ({"goal": {"weight": float("inf")}}, r"critics\.goal\.weight must be a finite number >= 0, got inf"),
    ({"collision": {"tasks": ["lane", "goal"]}}, r"critics\.collision is enabled for task kind 'lane', which it "
                                                  r"does not support; it supports \['goal'\]"),
    ({"lane_exit": {"discount": 0.0}}, r"critics\.lane_exit\.discount must lie in \(0\.0, 1\.0\], got 0\.0"),
    ({"speed": {"along_lane": 1}}, r"critics\.speed\.along_lane must be true or false, got 1"),
    ({"deviation": {"enabled": "yes"}}, r"critics\.deviation\.enabled must be true or false"),
])
def test_bad_critic_settings_are_refused_at_start_naming_them(critics: dict, words: str) -> None:
    with pytest.raises(ValueError, match=words):
        PlannerConfig(critics=critics)


def test_the_old_weight_fields_are_gone_with_a_clear_error() -> None:
    with pytest.raises(ValueError, match="w_speed"):
        PlannerConfig(w_speed=4.0)  # type: ignore[call-arg]


# a stateful critic: one module (written beside the script) and one registration line (in the script). Its value is a
# ramp carried from step to step: `first` at the first step, plus `growth` after each
STATEFUL_MODULE = r"""
from gpmppi.mppi.critics.base import Critic, Param, StepState, critic_term


@critic_term
def ramp_cost(weight, cost_w, p, geo, at, ramp):
    return weight * ramp * at.omega * at.omega


@critic_term
def first_ramp(cost_w, p):
    return cost_w[p]  # `first`


@critic_term
def next_ramp(ramp, cost_w, p):
    return ramp + cost_w[p + 1]  # `growth`


CRITIC = Critic("ramp", 0.5, ("lane", "goal"), ramp_cost, "ramp_k omega^2 per step, the ramp growing along the horizon",
                params={"first": Param(0.25, "the ramp at the first step"),
                        "growth": Param(0.5, "what the ramp grows by per step")},
                state=StepState(first_ramp, next_ramp))
"""

# a critic that is one module (here: this script) and one registration line
PLUGIN = r"""
import json, os, sys
import numpy as np
from gpmppi.mppi.critics import register
from gpmppi.mppi.critics.base import Critic, critic_term
import ramp_critic

register(ramp_critic.CRITIC)


@critic_term
def turning_cost(weight, cost_w, p, geo, at):
    return weight * at.omega * at.omega


register(Critic("turning", 0.5, ("lane", "goal"), turning_cost, "omega^2 per step [cost / (rad/s)^2]"))

from gpmppi.mppi import backends
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.mppi.synthetic import synthetic_model
from gpmppi.scenarios import circle_lane, paper_obstacle_scene

backend = sys.argv[1]
model = synthetic_model(nodes=4, n_train=20)
scored = []
split = backends.critic_costs
def recording_split(*bundles):  # the plan's nominal scoring, recorded to score the same sequence by the kernel
    scored.append(bundles)
    return split(*bundles)
backends.critic_costs = recording_split
out = {}
critics = {"turning": {"weight": 2.0}, "ramp": {"weight": 3.0, "growth": 0.75}}
for name, scenario in (("lane", circle_lane()), ("goal", paper_obstacle_scene())):
    p = Planner(PlannerConfig(backend=backend, samples=32, horizon=8, critics=critics), model)
    r = p.plan(scenario.start, scenario.task, np.array([0.5, 0.3, 0.2]))
    # the nominal sequence's cost by the CPU rollout kernel and this backend's, which must count the new critics as
    # the split does
    kernel_cost = float(backends.rollouts("cpu", *scored[-1], 1, 0)[1][0])
    backend_cost = float(backends.rollouts(backend, *scored[-1], 1, 0)[1][0])
    cost = p.kind(scenario.task).cost
    out[name] = {"critics": r.critic_costs, "cost": r.cost, "kernel_cost": kernel_cost, "backend_cost": backend_cost,
                 "sample_costs": r.sample_costs.tolist(), "weight": cost.weights["turning"]}
    p0 = Planner(PlannerConfig(backend=backend, samples=32, horizon=8, critics={"turning": {"enabled": False}}), model)
    off = p0.plan(scenario.start, scenario.task, np.array([0.5, 0.3, 0.2]))
    out[name]["sample_costs_off"] = off.sample_costs.tolist()
# the kinematic unicycle: the state after step k turns at the step's command, so the ramp's share is known
p = Planner(PlannerConfig(backend=backend, dynamics="unicycle", samples=32, horizon=8, critics=critics), model)
r = p.plan(circle_lane().start, circle_lane().task, np.array([0.5, 0.3, 0.2]))
out["unicycle"] = {"ramp": r.critic_costs["ramp"], "omega_ref": r.controls[:, 1].tolist()}
out["cache"] = os.environ["NUMBA_CACHE_DIR"]
print("RESULT", json.dumps(out))
"""


BACKENDS = ["cpu", "cuda"]
TEST_NAME = "test_a_new_critic_in_one_module_is_counted_by_the_kernels_and_reported"
STATEFUL_TEST_NAME = "test_a_new_stateful_critic_carries_its_value_along_the_horizon_on_both_backends"


class PluginRuns:
    """PLUGIN in a fresh process per backend, given a copy of this process's kernel cache, which holds the kernels of
    the package's own critics (in the suite: those `gpmppi warm` compiled): a kernel loaded from it would not know the
    new critics, so each run must cache apart (`kernel_cache.key_cache_to_outside_critics`: a folder keyed by the
    plug-ins' sources beside the one given). The CPU run starts at once and compiles the CPU kernels with the plug-in
    (~17 s on 2 cores); the CUDA run (the simulator, which also needs the CPU kernels: propagate, the per-critic split,
    the kernel cost it checks) starts when its test asks for it, in the CPU run's cache once that run is done (the
    same plug-ins, so the same keyed folder and kernels: ~25 s of CPU not spent compiling them again), or on its own
    when the CPU run was not selected."""

    def __init__(self, tmp_path_factory: pytest.TempPathFactory, wanted: set[str]) -> None:
        self._tmp = tmp_path_factory
        self.procs: dict[str, subprocess.Popen] = {}
        self.cache = tmp_path_factory.mktemp("plugin") / "cache"
        if kernel_cache.cache_folder().is_dir():
            shutil.copytree(kernel_cache.cache_folder(), self.cache)
        else:
            self.cache.mkdir()
        if "cpu" in wanted:
            self._start("cpu")

    def _start(self, backend: str) -> subprocess.Popen:
        d = self._tmp.mktemp(f"plugin-{backend}")
        script = d / "turning_critic.py"
        script.write_text(PLUGIN)
        (d / "ramp_critic.py").write_text(STATEFUL_MODULE)
        settings = {"NUMBA_CACHE_DIR": str(self.cache), "PYTHONWARNINGS": "ignore::RuntimeWarning"}
        # CUDA: the simulator, or the GPU where the tests run on one (tests/cuda_mode.py)
        env = cuda_env(**settings) if backend == "cuda" else dict(os.environ, **settings)
        with (d / "stdout").open("w") as out, (d / "stderr").open("w") as err:  # files: no pipe fills up
            self.procs[backend] = subprocess.Popen([sys.executable, str(script), backend], cwd=REPO, env=env,
                                                   stdout=out, stderr=err, text=True)
        return self.procs[backend]

    def run(self, backend: str) -> subprocess.Popen:
        """The finished run of `backend` (started now if it was not)."""
        if backend == "cuda" and "cuda" not in self.procs:
            if "cpu" in self.procs:
                self.procs["cpu"].wait(timeout=900)  # its kernels in the shared cache first
            self._start("cuda")
        proc = self.procs[backend]
        proc.wait(timeout=900)
        return proc


@pytest.fixture(scope="module")
def plugin_runs(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[PluginRuns]:
    """The plug-in runs of the backends whose test is selected (`PluginRuns`)."""
    wanted = {item.callspec.params["backend"] for item in request.session.items
              if item.module is request.module
              and getattr(item, "originalname", "") in (TEST_NAME, STATEFUL_TEST_NAME)}
    runs = PluginRuns(tmp_path_factory, wanted)
    yield runs
    for proc in runs.procs.values():  # a failed test leaves no compiling process behind
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.slow(seconds=45)  # the kernels compiled with the plug-in in a fresh cache (the CUDA run in the CPU run's)
@pytest.mark.parametrize("backend", BACKENDS)
def test_a_new_critic_in_one_module_is_counted_by_the_kernels_and_reported(
    backend: str, plugin_runs: PluginRuns
) -> None:
    proc = plugin_runs.run(backend)
    folder = Path(proc.args[1]).parent
    stdout, stderr = (folder / "stdout").read_text(), (folder / "stderr").read_text()
    assert proc.returncode == 0, stderr[-3000:]
    out = json.loads(stdout.split("RESULT ", 1)[1])
    # cached apart from the package's own kernels (the copy it was given), in a folder named by the plug-ins
    assert out["cache"].startswith(f"{plugin_runs.cache}-critics-"), out["cache"]
    for name in ("lane", "goal"):
        r = out[name]
        assert list(r["critics"])[-1] == "turning" and r["critics"]["turning"] > 0.0, (name, r["critics"])
        assert sum(r["critics"].values()) == r["cost"], name
        assert r["cost"] == pytest.approx(r["kernel_cost"], rel=1e-8), name  # the kernel counts it as the split
        # the backend's kernel counts it: the same samples (same seed) cost more with it than without
        pairs = list(zip(r["sample_costs"], r["sample_costs_off"], strict=True))
        assert all(on >= off for on, off in pairs) and any(on > off for on, off in pairs), name


def _plugin_result(backend: str, plugin_runs: PluginRuns) -> dict:
    proc = plugin_runs.run(backend)
    folder = Path(proc.args[1]).parent
    stdout, stderr = (folder / "stdout").read_text(), (folder / "stderr").read_text()
    assert proc.returncode == 0, stderr[-3000:]
    return json.loads(stdout.split("RESULT ", 1)[1])


@pytest.mark.slow(seconds=45)  # shares the plug-in runs of the test above (the same script, both critics)
@pytest.mark.parametrize("backend", BACKENDS)
def test_a_new_stateful_critic_carries_its_value_along_the_horizon_on_both_backends(
    backend: str, plugin_runs: PluginRuns
) -> None:
    out = _plugin_result(backend, plugin_runs)
    # its value at step k: first + k * growth (the config's growth, the module's default first), added step by step
    ramp, expected = 0.25, 0.0
    for omega in out["unicycle"]["omega_ref"]:
        expected += 3.0 * ramp * omega * omega
        ramp += 0.75
    assert out["unicycle"]["ramp"] == pytest.approx(expected, rel=1e-12)
    for name in ("lane", "goal"):
        r = out[name]
        assert r["critics"]["ramp"] > 0.0 and sum(r["critics"].values()) == r["cost"], name
        # the CPU kernel and this backend's kernel (the CUDA simulator's for cuda) carry the value as the split does
        assert r["cost"] == pytest.approx(r["kernel_cost"], rel=1e-8), name
        assert r["cost"] == pytest.approx(r["backend_cost"], rel=1e-8), name
