"""`gpmppi warm` (run by deploy/setup.sh) compiles what the services compile at start: after it, a planner and a
sim service of the shipped configuration start without compiling anything (numba reports every kernel it loads
from or saves to its cache with NUMBA_DEBUG_CACHE=1), and the planner announces no compile."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from zenoh_helpers import Collector, ServiceProcess, free_port, heartbeats, router, settings, wait_for

from tools.warm import shipped_planner_configs

REPO = Path(__file__).resolve().parents[1]


def test_every_shipped_launch_file_with_a_planner_is_warmed() -> None:
    sources = {name for name, _ in shipped_planner_configs()}
    with_planner = {p.name for p in [REPO / "services" / "launch" / "default.yaml", *(REPO / "deploy").glob("*.yaml")]
                    if "name: planner" in p.read_text()}
    assert "default.yaml" in sources
    assert sources == with_planner


@pytest.mark.slow  # in a fresh checkout it compiles the shipped planner (the planner tests then load it)
def test_after_warm_planner_and_sim_start_without_compiling(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    warm = subprocess.run([sys.executable, "-m", "tools.cli", "warm"], cwd=REPO, capture_output=True, text=True,
                          timeout=1500)
    assert warm.returncode == 0, warm.stderr[-3000:]
    assert "planner on circle" in warm.stdout, warm.stdout
    monkeypatch.setenv("NUMBA_DEBUG_CACHE", "1")
    port = free_port()
    with router(port) as session:
        col = Collector(session)
        services = [ServiceProcess(kind, settings(kind, port, robot="r1"), tmp_path) for kind in ("planner", "sim")]
        try:
            # the planner's heartbeat starts with its loop, after its warm-up plan (compiled or loaded)
            assert wait_for(lambda: all(heartbeats(col, "r1", k) for k in ("planner", "sim")), 120.0), [
                s.log()[-2000:] for s in services
            ]
        finally:
            codes = [s.stop() for s in services]
    assert codes == [0, 0]
    planner_log, sim_log = (s.log() for s in services)
    assert "[cache] data loaded" in planner_log, planner_log[-3000:]  # the debug output is there at all
    for log in (planner_log, sim_log):
        compiled = [line for line in log.splitlines() if "[cache]" in line and "saved" in line]
        assert not compiled, compiled
    # and the planner knows it: the warm-up recorded its kernels where the service looks, so no compile notice
    assert "compiling planner kernels" not in planner_log, planner_log[-3000:]


WARMED_LIVE_PATH = r"""
import numpy as np
from gpmppi.mppi import kernel_cache
from gpmppi.mppi.planner import Planner
from services.planner import Settings, load_model, warm_up_scenario

settings = Settings()
planner = Planner(settings.planner, load_model(settings.model_file))
scenario = warm_up_scenario(settings.scenario)
start = np.asarray(scenario.start, dtype=np.float64)
planner.warm_up(start, scenario.task)
before = kernel_cache.cache_counts()
# what the live loop does in its first seconds: the terrain service's weights, prepared between states, then held
for w in ([0.5, 0.3, 0.2], [0.5, 0.3, 0.2], [0.2, 0.2, 0.6]):
    planner.prepare(np.array(w))
    planner.plan(start, scenario.task, np.array(w), delay_s=0.1)
use = kernel_cache.kernels_used(before, kernel_cache.cache_counts())
print("LIVE", sorted(use.loaded), sorted(use.compiled))
"""


@pytest.mark.slow(seconds=8)
def test_after_the_planners_warm_up_its_first_weights_load_and_compile_nothing() -> None:
    """The planner's warm-up (`Planner.warm_up`, the service's and `gpmppi warm`'s) plans the live loop's first seconds:
    new terrain weights collapsed ahead and held. Before, it planned once on the uniform start only, and a fresh
    install compiled the table's collapse at the terrain service's first weights, between two commands (1.1 and 0.4
    s on 2 cores: egress's watchdog sent zero in the demo). In a fresh process, so no other test's kernels count."""
    run = subprocess.run([sys.executable, "-c", WARMED_LIVE_PATH], cwd=REPO, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    live = [line for line in run.stdout.splitlines() if line.startswith("LIVE")]
    assert live == ["LIVE [] []"], run.stdout[-2000:]


def test_the_warm_up_leaves_the_plans_as_a_fresh_planner_makes_them() -> None:
    """`Planner.warm_up` ends in `reset`: the plans after it are a fresh planner's, to the bit (the table collapsed
    for the warm-up's weights is collapsed again for the live ones)."""
    import numpy as np
    from cached_models import shipped_model

    from gpmppi.mppi.planner import Planner, PlannerConfig
    from gpmppi.scenarios import circle_lane

    model, sc = shipped_model(), circle_lane()
    config = PlannerConfig(samples=128, seed=3)
    warmed, fresh = Planner(config, model), Planner(config, model)
    warmed.warm_up(sc.start, sc.task)
    w = np.array([0.6, 0.3, 0.1])
    for planner in (warmed, fresh):
        planner.prepare(w)
    a, b = warmed.plan(sc.start, sc.task, w), fresh.plan(sc.start, sc.task, w)
    assert a.controls.tobytes() == b.controls.tobytes() and a.cost == b.cost
