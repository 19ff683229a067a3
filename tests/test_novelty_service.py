"""The terrain service says when the ground is new, as a real process over loopback Zenoh: a drive recorded on the
physics plant (grass, then sand, which the shipped profile was not trained on) is published as states and commands;
its `TerrainWeights` carry P(unknown) above 0.5 and `unknown_active` after the change, its heartbeat the flag
`unknown_ground` and the count `unknown_entered`, and its log one line naming the change."""

from __future__ import annotations

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

from gpmppi.plant.physics import PhysicsPlant
from gpmppi.plant.terrains import load_terrains
from schemas import Command, Header, State, TerrainWeights, decode, encode

NS = 1_000_000_000
SWITCH_S = 8.0


def _drive() -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(stamp, measured state, command) every 0.1 s: smooth driving on grass, then on sand."""
    plant = PhysicsPlant(load_terrains(None), "grass", seed=4, noise=True)
    plant.reset(np.zeros(5))
    out = []
    for k in range(int((SWITCH_S + 4.0) / 0.1)):
        t = 0.1 * k
        if abs(t - SWITCH_S) < 1e-9:
            plant.set_terrain("sand")
        u = np.array([min(1.3, 0.5 * t), 0.4 * np.sin(0.5 * t)])
        out.append((round(t * NS), plant.measure(), u))
        plant.step(u, 0.1)
    return out


@pytest.mark.slow(seconds=10)
def test_the_terrain_service_publishes_unknown_ground_and_says_it_in_its_health(tmp_path: Path) -> None:
    drive = _drive()
    port = free_port()
    cfg = settings("terrain", port, heartbeat_hz=10.0, command_source="cmd", pairing="stamp")
    with router(port):
        observer = client(port)
        col = Collector(observer)
        terrain = ServiceProcess("terrain", cfg, tmp_path)
        try:
            assert wait_for(lambda: bool(heartbeats(col, "r1", "terrain")), 60.0), terrain.log()
            states = matched_publisher(observer, "gpmppi/r1/state")
            commands = matched_publisher(observer, "gpmppi/r1/cmd")
            base = time.time_ns()
            for stamp, x, u in drive:  # faster than real time: the service pairs and gates by the stamps
                header = Header(stamp_ns=base + stamp)
                states.put(encode(State(x=x[0], y=x[1], theta=x[2], v=x[3], omega=x[4], header=header)))
                commands.put(encode(Command(v_ref=float(u[0]), omega_ref=float(u[1]), header=header)))
                time.sleep(0.03)

            def weights() -> list[TerrainWeights]:
                return [decode(TerrainWeights, p) for _, p, _ in col.on("gpmppi/r1/terrain/weights")]

            last = base + drive[-1][0]
            assert wait_for(lambda: any(w.header.stamp_ns == last for w in weights()), 10.0), terrain.log()
            switch = base + round(SWITCH_S * NS)
            before = [w for w in weights() if base + 3 * NS <= w.header.stamp_ns < switch]
            after = [w for w in weights() if w.header.stamp_ns >= switch]
            assert before and max(w.unknown for w in before) < 0.5 and not any(w.unknown_active for w in before)
            first = next(w.header.stamp_ns for w in after if w.unknown > 0.5)
            assert (first - switch) / NS <= 3.0 and after[-1].unknown_active
            assert wait_for(lambda: any(h.flags.get("unknown_ground") and h.counts.get("unknown_entered") == 1
                                        for h in heartbeats(col, "r1", "terrain")), 5.0), heartbeats(col, "r1",
                                                                                                     "terrain")[-1]
            assert "ground unknown" in terrain.log()
        finally:
            assert terrain.stop() == 0
