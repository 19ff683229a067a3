"""The closed loop runs the deployed command path: egress's limits show in the commands the base receives, and the
services' own event loops (terrain and egress, `serve`, in this process over real loopback Zenoh sessions) fed the
closed loop's recorded states and planner commands give the same terrain weights and base commands."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from zenoh_helpers import Collector, client, free_port, matched_publisher, router, settings, wait_for

from gpmppi.evaluation.closed_loop import ClosedLoopConfig, Trajectory, run_closed_loop
from gpmppi.evaluation.runner import EvalSettings, cached_gp_model, make_planner, make_plant
from gpmppi.safety import SafetyConfig
from gpmppi.scenarios import circle_lane
from gpmppi.terrain.cycle import TerrainCycleConfig
from gpmppi.terrain.estimator import make_estimator
from gpmppi.terrain.settings import EstimatorConfig
from schemas import BaseCommand, Command, Header, State, TerrainWeights, decode, encode
from services import egress, terrain
from services.runtime.node import Node

EVAL = EvalSettings(samples=256)


def _loop(safety: SafetyConfig | None, seconds: float, cycle: TerrainCycleConfig | None = None) -> Trajectory:
    scenario = circle_lane()
    model = cached_gp_model(None)
    plant = make_plant(EVAL, "asphalt", 0)
    cfg = ClosedLoopConfig(time_limit_s=seconds, safety=safety, terrain=cycle or TerrainCycleConfig())
    return run_closed_loop(make_planner(EVAL, "gp", "asphalt", 0), plant, scenario.task, scenario.start,
                           model.n_terrains, cfg, estimator=make_estimator(model, EstimatorConfig()),
                           initial_terrain="asphalt")


@pytest.mark.slow
def test_egress_limits_bind_and_show_in_the_base_commands() -> None:
    limits = SafetyConfig(accel_limit=0.5, decel_limit=1.0, yaw_accel_limit=1.0, yaw_decel_limit=2.0)
    run = _loop(limits, 3.0)
    free = _loop(SafetyConfig(), 3.0)
    t, u, reasons = run.base_times, run.base_commands, run.base_reasons
    assert t.size >= 2 * run.commands.shape[0]  # each command, and a repeat at 20 Hz between planner cycles
    assert np.allclose(np.diff(t)[2:], 0.05, atol=1e-6)  # outputs every 50 ms (latency 0: commands on the grid)
    rate = np.abs(np.diff(u, axis=0)) / np.diff(t)[:, None]
    # up from standstill: the v ramp is the acceleration limit; omega never changes faster than its larger limit
    assert np.max(rate[:, 0]) <= 1.0 + 1e-6 and np.max(rate[:, 1]) <= 2.0 + 1e-6
    assert reasons.count("limit") > len(reasons) // 2
    ramp = u[1:21, 0]  # the first second: 0.025 m/s per output, the planner asks for far more
    assert np.allclose(np.diff(ramp), 0.5 * 0.05, atol=1e-9)
    assert np.max(np.abs(np.diff(free.base_commands[:, 0]))) / 0.05 > 2.0  # unlimited, the planner's steps show
    # the planner's commands are not what the base got: at each planner cycle, the base's output at that time
    at_cycle = u[np.searchsorted(t, run.times[:-1] + 1e-9) - 1]
    assert np.max(run.commands[:, 0] - at_cycle[:, 0]) > 0.2
    assert np.mean(run.true_states[:, 3]) < np.mean(free.true_states[:, 3]) - 0.2  # and the robot drove slower


def _thread(target, *args) -> threading.Thread:
    thread = threading.Thread(target=target, args=args, daemon=True)
    thread.start()
    return thread


@pytest.mark.slow
def test_the_services_event_loops_give_the_closed_loops_weights_and_base_commands() -> None:
    # limits that never bind (a budget of 1e9 m/s^2 times even 1 us since the last output is 1000 m/s): egress's
    # first output for a command is then the command, whatever the wall-clock
    # spacing of its outputs; a long command wait, so a loaded machine's egress hop never leaves a state unpaired
    safety = SafetyConfig(accel_limit=1e9, decel_limit=1e9, yaw_accel_limit=1e9, yaw_decel_limit=1e9)
    # pairing by stamp: 'applied' averages the outputs by their arrival, which over Zenoh is the wall clock's
    # (tests/test_terrain_cycle.py checks it; tools/stack_terrain.py replays a stack's log with it)
    cycle = TerrainCycleConfig(command_wait_s=1.0, pairing="stamp")
    run = _loop(safety, 4.0, cycle)
    model = cached_gp_model(None)
    stamps = np.round(run.times[: run.commands.shape[0]] * 1e9).astype(np.int64)
    port = free_port()
    with router(port):
        eg_settings = egress.Settings(**settings("egress", port, **safety.model_dump()))
        te_settings = terrain.Settings(**settings("terrain", port, **cycle.model_dump()))
        nodes = [Node(eg_settings, install_signals=False).open(), Node(te_settings, install_signals=False).open()]
        threads = [
            _thread(egress.serve, nodes[0], eg_settings),
            _thread(terrain.serve, nodes[1], te_settings, model, make_estimator(model, te_settings.estimator)),
        ]
        observer = client(port)
        try:
            # the observer listens to the outputs only, so the publishers below match the services' subscribers
            col = Collector(observer, "gpmppi/r1/terrain/weights")
            base_col = Collector(observer, "gpmppi/r1/base/cmd")
            state_pub = matched_publisher(observer, "gpmppi/r1/state")
            cmd_pub = matched_publisher(observer, "gpmppi/r1/cmd")
            time.sleep(0.5)  # and terrain's subscription to egress's base/cmd has reached the router
            t0 = time.time_ns()  # the recorded stamps, shifted to now: egress checks command ages by this clock
            weights: dict[int, TerrainWeights] = {}
            for k, stamp in enumerate(stamps):
                s = int(t0 + stamp)
                # in real time: egress refuses commands stamped ahead of its clock (max_command_future_s)
                time.sleep(max(0.0, (s - time.time_ns()) / 1e9))
                x = run.measured_states[k]
                state_pub.put(encode(State(x=x[0], y=x[1], theta=x[2], v=x[3], omega=x[4], header=Header(stamp_ns=s))))
                cmd_pub.put(encode(Command(v_ref=run.commands[k, 0], omega_ref=run.commands[k, 1],
                                           header=Header(stamp_ns=s))))

                def solved(s: int = s) -> bool:
                    got = [decode(TerrainWeights, p) for _, p, _ in col.on("gpmppi/r1/terrain/weights")]
                    weights.update({w.header.stamp_ns: w for w in got})
                    return s in weights

                assert wait_for(solved, 5.0), f"no weights for state {k}"
        finally:
            for node in nodes:
                node.stop()
            for thread in threads:
                thread.join(5.0)
            for node in nodes:
                node.close()
            observer.close()
    # weights: one solve per state, the same numbers (the service publishes them in its own terrain order: by name)
    assert len(run.terrain_solves) == len(stamps)
    for _, stamp, w, ok in run.terrain_solves:
        msg = weights[int(t0 + stamp)]
        by_name = dict(zip(msg.names, msg.weights, strict=True))
        assert np.allclose([by_name[n] for n in model.terrains], w, rtol=0, atol=1e-12), stamp
        assert msg.solver_ok == ok
    # base commands: egress's first output for each command (stamped with it) is the closed loop's
    base = {b.header.stamp_ns: b for b in (decode(BaseCommand, p) for _, p, _ in base_col.on("gpmppi/r1/base/cmd"))}
    firsts = [i for i, r in enumerate(run.base_reasons) if r == "planner" and np.any(
        np.isclose(run.base_times[i], run.times[: len(stamps)], atol=1e-9))]
    assert len(firsts) == len(stamps)
    for i, stamp in zip(firsts, stamps, strict=True):
        b = base[int(t0 + stamp)]
        assert (b.v, b.omega, b.reason) == (run.base_commands[i, 0], run.base_commands[i, 1], "planner")
