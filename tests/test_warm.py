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
