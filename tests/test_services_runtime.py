"""The node runtime's scheduling over real Zenoh sessions on loopback: input wakes a waiting loop at once (no
polling interval), FIFO subscriptions keep every message in order, stop ends a wait, process settings (nice,
numba threads), and the terrain service's start (prior first, then solved weights paired by stamp)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from zenoh_helpers import (
    REPO,
    Collector,
    ServiceProcess,
    client,
    endpoint,
    free_port,
    put_state_and_base_command,
    router,
    settings,
    wait_for,
)

from schemas import Command, State, TerrainWeights, decode
from services.runtime.node import Node
from services.runtime.node_settings import NodeSettings, ZenohSettings


def _node(name: str, port: int, **extra: object) -> Node:
    zs = ZenohSettings(mode="client", connect=[endpoint(port)])
    return Node(NodeSettings(service=name, robot="r1", zenoh=zs, **extra), install_signals=False)


def test_input_ends_the_idle_wait_and_stop_ends_it_too() -> None:
    port = free_port()
    with router(port):
        # an idle wait of 60 s and no heartbeat due for 100 s: only the arriving message can end it early
        sender, receiver = _node("a", port), _node("b", port, poll_s=60.0, heartbeat_hz=0.01)
        with sender, receiver:
            pub = sender.publisher("state")
            sub = receiver.subscribe("state")
            receiver.spin_once(0.0)  # the first heartbeat goes out now; the next one is 100 s away
            assert wait_for(lambda: (pub.put(State(x=0, y=0, theta=0, v=0, omega=0)), sub.take())[1] is not None, 5.0)
            threading.Timer(0.3, lambda: pub.put(State(x=1.0, y=0, theta=0, v=0, omega=0))).start()
            t0 = time.monotonic()
            got = None
            while got is None and time.monotonic() - t0 < 30.0:
                receiver.spin_once()
                if (msg := sub.take()) is not None and msg.x == 1.0:  # (a late warm-up message may come first)
                    got = msg
            assert got is not None
            assert time.monotonic() - t0 < 30.0, "the loop slept through the message"
            threading.Timer(0.3, receiver.stop).start()
            t0 = time.monotonic()
            receiver.spin_once()
            assert not receiver.ok() and time.monotonic() - t0 < 30.0


def test_fifo_subscription_keeps_every_message_in_order_past_its_capacity() -> None:
    port = free_port()
    with router(port):
        sender, receiver = _node("a", port), _node("b", port)
        with sender, receiver:
            pub = sender.publisher("cmd")
            sub = receiver.subscribe("cmd", newest_only=False, capacity=4)
            newest = receiver.subscribe("cmd")
            # routes up: warm-up messages (v_ref -1) until one arrives; late ones are told apart by their value
            assert wait_for(lambda: (pub.put(Command(v_ref=-1, omega_ref=0)), newest.take())[1] is not None, 5.0)
            for i in range(40):  # ten times the capacity while nobody drains: the sender waits, nothing drops
                pub.put(Command(v_ref=float(i), omega_ref=0.0))
            got: list[Command] = []
            assert wait_for(lambda: (got.extend(sub.drain()), len(got) >= 40 and got[-1].v_ref == 39.0)[1], 10.0)
            assert [c.v_ref for c in got if c.v_ref >= 0] == [float(i) for i in range(40)]
            last = newest.take()
            assert last is not None and last.v_ref == 39.0 and newest.take() is None  # newest-only: one kept


def test_newest_only_counts_every_bad_message_a_newer_one_replaced_before_the_loop_took_it() -> None:
    port = free_port()
    with router(port):
        sender, receiver = _node("a", port), _node("b", port)
        with sender, receiver:
            pub = sender.publisher("state")
            sub = receiver.subscribe("state")
            assert wait_for(lambda: (pub.put(State(x=0, y=0, theta=0, v=0, omega=0)), sub.take())[1] is not None, 5.0)
            time.sleep(0.2)
            sub.take()  # a late warm-up message
            bad = [b"{bad json", b'{"x": NaN, "y": 0, "theta": 0, "v": 0, "omega": 0}',
                   b'{"header": {"schema_version": 7}, "x": 0, "y": 0, "theta": 0, "v": 0, "omega": 0}']
            raw = sender.session.declare_publisher(sender.key("state"))
            # a burst while the loop takes nothing (a plan in progress): each bad one is replaced by the next
            for payload in bad:
                raw.put(payload)
            pub.put(State(x=2.0, y=0, theta=0, v=0, omega=0))
            # counted on arrival, though the loop never took them; the loop still gets the newest, and only it
            assert wait_for(lambda: receiver.counters.rejected == len(bad), 10.0), receiver.counters.rejected
            newest = sub.take()
            assert newest is not None and newest.x == 2.0 and sub.take() is None
            assert receiver.counters.received >= len(bad) + 1


def test_process_settings_lower_priority_and_set_numba_threads() -> None:
    code = (
        "import os\n"
        "from services.runtime.node_settings import NodeSettings\n"
        "from services.runtime.scheduling import apply_process_settings\n"
        "before = os.nice(0)\n"
        "apply_process_settings(NodeSettings(nice=3, numba_threads=-1))\n"
        "print(os.nice(0) - before, os.environ['NUMBA_NUM_THREADS'])\n"
        "import numba\n"
        "print(numba.config.NUMBA_NUM_THREADS)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=env, timeout=120, check=True
    ).stdout.split()
    expected = str(max(1, (os.cpu_count() or 1) - 1))
    assert out == ["3", expected, expected], out
    with pytest.raises(ValueError, match="numba_threads"):
        NodeSettings(numba_threads=0)


def test_terrain_comes_up_with_the_prior_then_solves_from_stamp_paired_commands(tmp_path: Path) -> None:
    from cached_models import shipped_model

    from gpmppi.models.dynamic_unicycle import velocity_step_exact

    model = shipped_model()
    port = free_port()
    with router(port):
        observer = client(port)
        col = Collector(observer, "gpmppi/r1/terrain/weights")
        proc = ServiceProcess("terrain", settings("terrain", port, command_wait_s=0.05), tmp_path)
        try:
            feeder = client(port)
            state_pub = feeder.declare_publisher("gpmppi/r1/state")
            cmd_pub = feeder.declare_publisher("gpmppi/r1/base/cmd")
            x = np.array([0.0, 0.0, 0.0, 0.5, 0.0])
            u = np.array([1.0, 0.3])
            t_ns = time.time_ns()

            def step() -> bool:
                # states at dt = 0.1 s moved by the nominal model; the command for each state carries its stamp
                nonlocal x, t_ns
                put_state_and_base_command(state_pub, cmd_pub, x, u, t_ns)
                v, w = velocity_step_exact(model.theta, x[3:4].copy(), x[4:5].copy(), u[0:1].copy(), u[1:2].copy(), 0.1)
                x = np.array([x[0], x[1], x[2], v[0], w[0]])
                t_ns += 100_000_000
                return any(decode(TerrainWeights, p).solver_ok for _, p, _ in col.on("gpmppi/r1/terrain/weights"))

            assert wait_for(step, 60.0, step=0.1), proc.log()[-3000:]
            msgs = [decode(TerrainWeights, p) for _, p, _ in col.on("gpmppi/r1/terrain/weights")]
            first = msgs[0]
            assert first.names == model.terrains and not first.solver_ok
            assert np.allclose(first.weights, 1 / len(model.terrains))
            solved = next(m for m in msgs if m.solver_ok)
            assert abs(sum(solved.weights) - 1.0) < 1e-6 and all(0.0 <= w <= 1.0 for w in solved.weights)
            feeder.close()
        finally:
            code = proc.stop()
            observer.close()
    assert code == 0, proc.log()[-3000:]
