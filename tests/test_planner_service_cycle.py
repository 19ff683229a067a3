"""The planner service as a real process over loopback Zenoh: it says in its log when it has to compile its
kernels (an empty numba cache) and says nothing of the kind when they are cached; and its commands are those of
a `PlannerCycle` driven directly with the same states, bit for bit. Plus the cache check itself, in-process."""

from __future__ import annotations

import math
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from zenoh_helpers import (
    Collector,
    ServiceProcess,
    client,
    free_port,
    heartbeats,
    matched_publisher,
    router,
    settings,
    wait_for,
)

from gpmppi.mppi import kernel_cache
from gpmppi.mppi.cycle import Planned, PlannerCycle
from gpmppi.mppi.cycle_config import CycleConfig
from schemas import Command, Header, State, decode, encode

NOTICE = "compiling planner kernels for gp/grid on cpu (not cached yet"


def _states(n: int) -> list[np.ndarray]:
    """Along the circle lane from its start (radius 20 m, heading +y), 0.1 m apart at 1 m/s: no odometry jump."""
    return [np.array([20.0, 0.1 * k, math.pi / 2, 1.0, 0.05]) for k in range(n)]


def _cache_without_propagate(folder: Path) -> Path:
    """A copy of this process's kernel cache without `dynamics.propagate`, one kernel of the configuration.

    The service finds the configuration not cached and compiles that one kernel (seconds) against the rest, loaded:
    the notice and the compile are those of a cold cache, without the ~25 s of CPU a whole compile costs (where
    this process's cache is empty, it compiles everything). The rollout kernel is not the one taken out: on a cold
    cache it is compiled in a second process (`gpmppi.mppi.compile_ahead`, tested on its own)."""
    from gpmppi.mppi.dynamics import propagate

    source = kernel_cache.cache_folder()
    if source.is_dir():
        shutil.copytree(source, folder)
    else:
        folder.mkdir()
    index = Path(propagate._cache._cache_file._index_path)
    stem = index.name.removesuffix(".nbi")
    for path in (folder / index.parent.relative_to(source)).glob(f"{stem}.*"):
        path.unlink()  # the index and its data files
    return folder


@pytest.mark.slow
@pytest.mark.timeout(1800)  # one cold compile in the service: minutes, more on a loaded machine
def test_planner_service_announces_a_cold_compile_and_plans_as_the_cycle(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cache = _cache_without_propagate(tmp_path / "numba")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))  # the services' cache (this process has its own already)
    port = free_port()
    cfg = settings("planner", port, heartbeat_hz=5.0, compensate_delay=False, planner={"samples": 64, "backend": "cpu"})
    sent: list[tuple[int, np.ndarray]] = []
    with router(port):
        observer = client(port)
        col = Collector(observer)
        (tmp_path / "cold").mkdir()
        cold = ServiceProcess("planner", cfg, tmp_path / "cold")
        try:
            # the notice comes before the compile, not after it
            assert wait_for(lambda: NOTICE in cold.log(), 60.0), cold.log()
            assert not heartbeats(col, "r1", "planner") and "compiled planner kernels" not in cold.log()
            assert wait_for(lambda: bool(heartbeats(col, "r1", "planner")), 900.0), cold.log()
            state_pub = matched_publisher(observer, "gpmppi/r1/state")

            def commands() -> dict[int, Command]:
                return {(c := decode(Command, p)).header.stamp_ns: c for _, p, _ in col.on("gpmppi/r1/cmd")}

            for x in _states(8):
                stamp = time.time_ns()
                state_pub.put(encode(State(x=x[0], y=x[1], theta=x[2], v=x[3], omega=x[4],
                                           header=Header(stamp_ns=stamp))))
                assert wait_for(lambda s=stamp: s in commands(), 20.0), cold.log()  # noqa: B023
                sent.append((stamp, x))
        finally:
            assert cold.stop(30.0) == 0
        log = cold.log()
        line = next(s for s in log.splitlines() if NOTICE in s)
        assert "about" in line and str(cache) in line, line
        assert "compiled planner kernels for gp/grid on cpu in" in log, log

        # a second start finds them cached: no notice, no compile
        (tmp_path / "warm").mkdir()
        n_beats = len(heartbeats(col, "r1", "planner"))
        warm = ServiceProcess("planner", cfg, tmp_path / "warm")
        try:
            assert wait_for(lambda: len(heartbeats(col, "r1", "planner")) > n_beats, 120.0), warm.log()
        finally:
            assert warm.stop(30.0) == 0
        assert "compiling planner kernels" not in warm.log() and "compiled planner kernels" not in warm.log()
        observer.close()
    got = commands()

    # the same states through a PlannerCycle in this process, warmed up as the service does
    from gpmppi.mppi.planner import Planner, PlannerConfig
    from services.planner import load_model, load_scenario

    scenario = load_scenario("circle")
    planner = Planner(PlannerConfig(samples=64, backend="cpu"), load_model(None))
    planner.plan(np.asarray(scenario.start, dtype=np.float64), scenario.task, delay_s=0.01)
    planner.reset()
    cycle = PlannerCycle(planner, scenario.task, CycleConfig(compensate_delay=False), len(planner.model.terrains))
    for stamp, x in sent:
        out = cycle.on_state(x, stamp, 0.0, stamp)
        assert isinstance(out, Planned)
        assert (got[stamp].v_ref, got[stamp].omega_ref) == (float(out.result.control[0]),
                                                            float(out.result.control[1])), stamp


def test_cache_check_needs_the_manifest_and_every_kernel_it_lists(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from cached_models import shipped_model

    from gpmppi.mppi.planner import Planner, PlannerConfig
    from gpmppi.scenarios import circle_lane

    monkeypatch.setattr(kernel_cache, "cache_folder", lambda: tmp_path)  # the manifest only; kernels stay numba's
    label = "gp/grid on cpu"
    assert not kernel_cache.is_cached(label)  # an empty folder: nothing planned with it yet
    estimate, source = kernel_cache.compile_estimate_s(label)
    assert estimate == kernel_cache.REFERENCE_COMPILE_S and "2 cores" in source
    sc = circle_lane()
    Planner(PlannerConfig(samples=64, backend="cpu"), shipped_model()).plan(sc.start, sc.task, delay_s=0.01)
    use = kernel_cache.kernels_used({}, kernel_cache.cache_counts())  # everything this process loaded or compiled
    names = {**use.loaded, **use.compiled}
    assert any(name.endswith(":rollout_worker") for name in names), names
    kernel_cache.record(label, use, 42.0)
    assert kernel_cache.is_cached(label)
    assert kernel_cache.compile_estimate_s(label) == (42.0, "as measured when this cache was last filled")
    # a listed signature numba's index does not hold: not cached
    manifest = next((tmp_path / "gpmppi-kernels").glob("*.json"))
    text = manifest.read_text()
    manifest.write_text(text.replace("float64", "float32", 1))
    assert not kernel_cache.is_cached(label)
    manifest.write_text(text.replace(":rollout_worker", ":no_such_kernel"))
    assert not kernel_cache.is_cached(label)


def test_compile_estimate_is_the_largest_compile_not_the_last(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(kernel_cache, "cache_folder", lambda: tmp_path)
    label = "gp/grid on cpu"

    def use(n: int) -> kernel_cache.KernelUse:
        out = kernel_cache.KernelUse()
        out.compiled.update({f"m:k{i}": ["(float64,)"] for i in range(n)})
        return out

    kernel_cache.record(label, use(5), 21.0)  # a whole cold compile
    assert kernel_cache.compile_estimate_s(label)[0] == 21.0
    kernel_cache.record(label, use(1), 0.5)  # one kernel missing, compiled alone
    kernel_cache.record(label, kernel_cache.KernelUse(), None)  # everything loaded
    assert kernel_cache.compile_estimate_s(label)[0] == 21.0
    kernel_cache.record(label, use(5), 18.0)  # the next whole compile is the new measurement
    assert kernel_cache.compile_estimate_s(label)[0] == 18.0


@pytest.mark.slow(seconds=15)
@pytest.mark.timeout(600)
def test_planner_service_on_trigger_rate_plans_at_its_rate_from_the_newest_state(tmp_path: Path) -> None:
    """`trigger: rate`: states at 20 Hz, plans at `rate_hz` (4 Hz), each from a state that had arrived, never one
    for every state (as `trigger: state` would: 20 a second)."""
    port = free_port()
    rate_hz, state_hz, seconds = 4.0, 20.0, 3.0
    cfg = settings("planner", port, heartbeat_hz=5.0, compensate_delay=False, trigger="rate", rate_hz=rate_hz,
                   planner={"samples": 64, "backend": "cpu"})
    with router(port):
        observer = client(port)
        col = Collector(observer)
        service = ServiceProcess("planner", cfg, tmp_path)
        try:
            assert wait_for(lambda: bool(heartbeats(col, "r1", "planner")), 300.0), service.log()
            state_pub = matched_publisher(observer, "gpmppi/r1/state")
            sent: list[int] = []

            def commands() -> list[Command]:
                return [decode(Command, p) for _, p, _ in col.on("gpmppi/r1/cmd")]

            states = iter(_states(1000))  # 0.1 m apart: at 20 Hz as at 2 m/s, along the lane (no jump)

            def put_state() -> None:
                x, stamp = next(states), time.time_ns()
                state_pub.put(encode(State(x=x[0], y=x[1], theta=x[2], v=x[3], omega=x[4],
                                           header=Header(stamp_ns=stamp))))
                sent.append(stamp)
                time.sleep(1.0 / state_hz)

            # until the first plan (the first states wake a planner still warming its caches), then a timed window
            for _ in range(400):
                put_state()
                if commands():
                    break
            n_before, t0 = len(commands()), time.monotonic()
            for _ in range(int(seconds * state_hz)):
                put_state()
            elapsed = time.monotonic() - t0
            time.sleep(0.3)
        finally:
            assert service.stop(30.0) == 0
        observer.close()
    got = commands()
    in_window = len(got) - n_before
    # never faster than the rate (one tick of slack at each end), and planning throughout the window
    assert in_window <= rate_hz * elapsed + 2, (in_window, elapsed, service.log()[-2000:])
    assert in_window >= 0.5 * rate_hz * elapsed, (in_window, elapsed, service.log()[-2000:])
    assert {c.header.stamp_ns for c in got} <= set(sent)  # each planned from a state that was sent
