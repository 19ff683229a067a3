"""The terrain service says when the ground is new, and which channel of the test says so, as a real process over
loopback Zenoh: a drive recorded on the physics plant (grass, then sand, which the shipped profile was not trained on;
or asphalt, then glare ice through a square lane's corner) is published as states and commands; its `TerrainWeights`
carry P(unknown) above 0.5 and `unknown_active` after the change, and the channel that flagged it (`unknown_channel`:
the one-step residual for sand, the free run's loss of grip for glare ice); its heartbeat the flags `unknown_ground`
and `unknown_free_run` and the count `unknown_entered`, and its log one line naming the change."""

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


def _drive(ground: str) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(stamp, measured state, command) every 0.1 s: smooth driving on grass, then on sand; or a lane's straight on
    asphalt and, from the switch, glare ice through GP-MPPI's commands of a square lane's corner."""
    if ground == "sand":
        plant = PhysicsPlant(load_terrains(None), "grass", seed=4, noise=True)
        steps = [np.array([min(1.3, 0.5 * t), 0.4 * np.sin(0.5 * t)]) for t in 0.1 * np.arange(int((SWITCH_S + 4.0)
                                                                                                 / 0.1))]
    else:
        from test_novelty_grip import SWITCH_S as CORNER_AT
        from test_novelty_grip import lane_commands

        assert CORNER_AT == SWITCH_S
        plant = PhysicsPlant(load_terrains("tests/data/new_grounds.yaml"), "asphalt", seed=4, noise=True)
        steps = list(lane_commands())
    plant.reset(np.zeros(5))
    out = []
    for k, u in enumerate(steps):
        t = 0.1 * k
        if abs(t - SWITCH_S) < 1e-9:
            plant.set_terrain(ground)
        out.append((round(t * NS), plant.measure(), u))
        plant.step(u, 0.1)
    return out


@pytest.mark.slow(seconds=10)
@pytest.mark.parametrize(("ground", "channel"), [("sand", "one-step"), ("glare_ice", "free-run")])
def test_the_terrain_service_publishes_unknown_ground_and_its_channel_and_says_it_in_its_health(
        tmp_path: Path, ground: str, channel: str) -> None:
    drive = _drive(ground)
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

            def raw() -> list[bytes]:
                return [bytes(p) for _, p, _ in col.on("gpmppi/r1/terrain/weights")]

            def weights() -> list[TerrainWeights]:
                return [decode(TerrainWeights, p) for p in raw()]

            last = base + drive[-1][0]
            assert wait_for(lambda: any(w.header.stamp_ns == last for w in weights()), 10.0), terrain.log()
            switch = base + round(SWITCH_S * NS)
            before = [w for w in weights() if base + 3 * NS <= w.header.stamp_ns < switch]
            after = [w for w in weights() if w.header.stamp_ns >= switch]
            assert before and max(w.unknown for w in before) < 0.5 and not any(w.unknown_active for w in before)
            first = next(w for w in after if w.unknown > 0.5)
            assert (first.header.stamp_ns - switch) / NS <= 3.0 and any(w.unknown_active for w in after)
            # the channel on the wire: in the JSON the recorder writes, and the same in every weights flagged after
            # the first (sand's free run stays far below its level on this gentle drive; glare ice's one-step
            # residual stays known ground's)
            assert first.unknown_channel == channel and first.header.schema_version >= 5
            assert all(w.unknown_channel == channel for w in after if w.unknown > 0.5)
            assert any(f'"unknown_channel":"{channel}"' in p.decode().replace(" ", "") for p in raw())
            assert weights()[0].unknown_channel == ""  # the prior, before any window was scored

            def flagged() -> bool:
                return any(h.flags.get("unknown_ground") and h.counts.get("unknown_entered") == 1
                           and h.flags.get("unknown_free_run") == (channel == "free-run")
                           for h in heartbeats(col, "r1", "terrain"))

            assert wait_for(flagged, 5.0), heartbeats(col, "r1", "terrain")[-1]
            assert "ground unknown" in terrain.log()
            assert ("free-run channel" in terrain.log()) == (channel == "free-run")
        finally:
            assert terrain.stop() == 0
