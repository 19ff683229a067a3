"""The planner service under faults, as a real process over loopback Zenoh: stale, future-stamped and
non-finite states refused and named in the heartbeat; terrain weights that go silent kept and flagged stale,
then replaced by the prior; an odometry jump resets the warm start. Plus the jump rule itself."""

from __future__ import annotations

import json
import math
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

from gpmppi.mppi.cycle import odometry_jump
from schemas import Command, Header, Heartbeat, Plan, State, TerrainWeights, decode, encode
from services.planner import Settings

NS = 1_000_000_000
START = (20.0, 0.0, math.pi / 2)  # the circle lane's start: (radius, 0) heading +y


def test_odometry_jump_rule() -> None:
    s = Settings()
    x0 = np.array([0.0, 0.0, 0.0, 2.0, 0.0])
    assert odometry_jump((0, x0), NS // 10, np.array([0.2, 0.0, 0.0, 2.0, 0.0]), s) is None  # 2 m/s for 0.1 s
    # a gap of 2 s at 2 m/s explains 4 m of travel
    assert odometry_jump((0, x0), 2 * NS, np.array([4.3, 0.0, 0.0, 2.0, 0.0]), s) is None
    jump = odometry_jump((0, x0), NS // 10, np.array([1.0, 0.0, 0.0, 2.0, 0.0]), s)
    assert jump is not None and "1.00 m" in jump
    stopped = np.zeros(5)
    assert odometry_jump((0, stopped), 5 * NS, np.array([0.6, 0.0, 0.0, 0.0, 0.0]), s) is not None
    # heading: wrapped across +-pi it is a small step, not a jump; a relocalisation by 1 rad is one
    a = np.array([0.0, 0.0, math.pi - 0.05, 0.0, 0.0])
    assert odometry_jump((0, a), NS // 10, np.array([0.0, 0.0, -math.pi + 0.05, 0.0, 0.0]), s) is None
    assert "heading" in (odometry_jump((0, a), NS // 10, np.array([0.0, 0.0, math.pi - 1.05, 0.0, 0.0]), s) or "")
    spinning = np.array([0.0, 0.0, 0.0, 0.0, 3.0])
    assert odometry_jump((0, spinning), NS // 10, np.array([0.0, 0.0, 0.75, 0.0, 3.0]), s) is None


def test_fallback_must_not_come_before_stale() -> None:
    with pytest.raises(ValueError, match="weights_fallback_after_s"):
        Settings(weights_stale_after_s=2.0, weights_fallback_after_s=1.0)


def _state(
    x: float = START[0], y: float = START[1], theta: float = START[2], stamp_ns: int | None = None,
    v: float = 0.0, omega: float = 0.0,
) -> State:
    return State(x=x, y=y, theta=theta, v=v, omega=omega, header=Header(stamp_ns=stamp_ns or time.time_ns()))


@pytest.mark.slow(seconds=12)
# alone: its phases are timed against 0.6 / 1.6 s staleness clocks; beside a compile, a heartbeat after the terrain
# came back was unhealthy once in CI (not reproduced alone or beside the compile tests), when they were timed by
# their arrivals here (now on the planner's own clock)
@pytest.mark.exclusive
def test_planner_refuses_bad_states_flags_silent_terrain_and_resets_on_jumps(tmp_path: Path) -> None:
    from cached_models import shipped_model

    terrains = list(shipped_model().terrains)
    port = free_port()
    cfg = settings(
        "planner", port, heartbeat_hz=10.0, weights_stale_after_s=0.6, weights_fallback_after_s=1.6,
        planner={"samples": 256},
    )
    with router(port):
        observer = client(port)
        col = Collector(observer)
        planner = ServiceProcess("planner", cfg, tmp_path)
        try:
            hb = lambda: heartbeats(col, "r1", "planner")  # noqa: E731
            assert wait_for(lambda: bool(hb()), 120.0), planner.log()
            state_pub = matched_publisher(observer, "gpmppi/r1/state")
            weights_pub = matched_publisher(observer, "gpmppi/r1/terrain/weights")

            def cmd_stamps() -> set[int]:
                return {decode(Command, p).header.stamp_ns for _, p, _ in col.on("gpmppi/r1/cmd")}

            # the phases are timed on the planner's own clock, not by arrivals here (a loaded machine delays the
            # plans and heartbeats on their way back, and this process's callbacks): a plan at when the planner
            # handed its command to Zenoh (its state's stamp + its state_to_cmd), a heartbeat at its stamp, both on
            # this process's monotonic clock (one host)
            wall_to_mono = (time.monotonic_ns() - time.time_ns()) / 1e9

            def plans() -> list[tuple[float, Plan]]:
                return [(m.header.stamp_ns / 1e9 + m.timings_ms["state_to_cmd"] / 1e3 + wall_to_mono, m)
                        for m in (decode(Plan, p) for _, p, _ in col.on("gpmppi/r1/plan"))]

            def drive(seconds: float, weights: list[float] | None = None) -> None:
                end = time.monotonic() + seconds
                while time.monotonic() < end:
                    state_pub.put(encode(_state()))
                    if weights is not None:
                        weights_pub.put(encode(TerrainWeights(names=terrains, weights=weights)))
                    time.sleep(0.1)

            def counted(name: str, n: int = 1) -> bool:
                return wait_for(lambda: any(h.counts.get(name, 0) >= n for h in hb()), 15.0)  # a heartbeat carries it

            # it plans from good states; the terrain service's first message is the prior (uniform)
            uniform = [1.0 / len(terrains)] * len(terrains)
            drive(1.0, weights=uniform)
            assert wait_for(lambda: bool(cmd_stamps()), 5.0), planner.log()
            # stale, future-stamped and non-finite states: refused, named, and no command from them
            t_prior = time.monotonic()
            stale = time.time_ns() - 2 * NS
            state_pub.put(encode(_state(stamp_ns=stale)))
            assert counted("state_stale"), hb()[-1]
            future = time.time_ns() + 1 * NS
            state_pub.put(encode(_state(stamp_ns=future)))
            assert counted("state_future"), hb()[-1]
            assert "future" in hb()[-1].last_error
            bad = json.loads(encode(_state()))
            bad["x"] = float("nan")
            state_pub.put(json.dumps(bad).encode())  # json writes NaN
            assert counted("state_nonfinite"), hb()[-1]
            state_pub.put(b'{"x": "here"}')
            assert counted("state_invalid"), hb()[-1]
            # finite but far outside the model (ingress lets it through): the rollouts diverge; no crash, no
            # non-finite output, and planning goes on from good states
            n_before = len(cmd_stamps())
            for _ in range(3):
                state_pub.put(encode(_state(v=-5.0, omega=20.0)))
                time.sleep(0.1)
            drive(0.5)
            assert planner.alive() and len(cmd_stamps()) > n_before, planner.log()
            refused = hb()[-1].counts
            assert refused.get("plan_nonfinite", 0) + refused.get("plan_invalid", 0) >= 1, refused
            drive(0.5)
            assert stale not in cmd_stamps() and future not in cmd_stamps()
            assert all(math.isfinite(c.v_ref) and math.isfinite(c.omega_ref)
                       for c in (decode(Command, p) for _, p, _ in col.on("gpmppi/r1/cmd")))
            assert planner.alive()
            # silent after the prior (the terrain service building its solver): nothing is stale, nothing changes
            drive(max(0.0, 1.0 - (time.monotonic() - t_prior)))
            assert all(not p.weights_stale for _, p in plans()) and not any(h.flags["weights_stale"] for h in hb())

            # terrain weights: used while fresh; silent: kept and flagged stale; later the prior
            w = [0.0] * len(terrains)
            w[0], w[-1] = 0.8, 0.2
            t_w = time.monotonic()
            drive(1.0, weights=w)
            t_silent = time.monotonic()
            drive(2.5)
            # from the first plan on the new weights, every one until the silence is on them and fresh
            fresh = [(t, p) for t, p in plans() if t_w < t < t_silent]
            on_w = [p.terrain_weights == pytest.approx(w) and not p.weights_stale for _, p in fresh]
            assert True in on_w, [(round(t - t_w, 2), p.terrain_weights) for t, p in fresh]
            assert fresh[on_w.index(True)][0] < t_w + 0.8 and all(on_w[on_w.index(True):]), [
                (round(t - t_w, 2), p.weights_stale, p.terrain_weights) for t, p in fresh]
            kept = [p for t, p in plans() if t_silent + 0.6 + 0.2 < t < t_silent + 1.6 - 0.2]
            assert kept and all(p.terrain_weights == pytest.approx(w) and p.weights_stale for p in kept), [
                (round(t - t_silent, 2), p.weights_stale, p.terrain_weights) for t, p in plans() if t > t_silent]
            prior = [p for t, p in plans() if t > t_silent + 1.6 + 0.3]
            assert prior and all(p.terrain_weights == pytest.approx(uniform) and p.weights_stale for p in prior)
            during: list[Heartbeat] = [h for h in hb() if h.flags.get("weights_stale")]
            assert during and all(h.status == "degraded" for h in during)
            assert hb()[-1].flags["weights_prior"] and hb()[-1].counts["weights_fallback"] == 1
            # terrain back: fresh again, status ok
            t_back = time.monotonic()
            drive(1.0, weights=w)
            back = [p for t, p in plans() if t > t_back + 0.3]
            t_end = time.monotonic()
            assert back and not back[-1].weights_stale and back[-1].terrain_weights == pytest.approx(w)
            # from the first heartbeat that is ok again, every one is (not from a fixed delay: on a loaded machine a
            # heartbeat written before the planner took the weights arrived later than t_back + 0.3 s once)
            beats = [(h.header.stamp_ns / 1e9 + wall_to_mono, h) for h in
                     (decode(Heartbeat, p) for _, p, _ in col.on("gpmppi/r1/health/planner"))]
            beats = [(t, h) for t, h in beats if t_back < t < t_end]
            healthy = [h.status == "ok" and not h.flags["weights_stale"] for _, h in beats]
            listed = "\n".join(f"{t - t_back:.2f} s: {h.status} {h.flags} {h.last_error}" for t, h in beats)
            assert True in healthy, listed
            first_ok = healthy.index(True)
            assert beats[first_ok][0] < t_back + 0.8 and all(healthy[first_ok:]), listed

            # an odometry jump (relocalised 5 m away) resets the warm start, once; small steps do not
            assert hb()[-1].counts.get("odom_jump", 0) == 0
            for _ in range(5):
                state_pub.put(encode(_state(x=START[0] + 5.0)))
                time.sleep(0.1)
            assert counted("odom_jump"), hb()[-1]
            time.sleep(0.3)
            assert hb()[-1].counts["odom_jump"] == 1
        finally:
            assert planner.stop(30.0) == 0
            observer.close()
    assert "warm start reset" in planner.log()
