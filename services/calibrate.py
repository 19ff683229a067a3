"""calibrate: the calibration drive. On each new state, the next command of an excitation that stays inside a free
area (`gpmppi.plant.calibration_drive.CalibrationDrive`), published on the planner's `cmd` key, so egress's limits,
watchdog and e-stop apply to it as to the planner; the ground's name on `terrain/label`, so the recording carries it.

It never publishes on a stale state (older than `max_state_age_s` by this host's clock): with no commands egress's
watchdog stops the robot. At the target (distance or time) it commands zero for `stop_s`, then reports `done` in its
heartbeat (flag) and keeps commanding zero on each state until it is stopped. Its heartbeat counts the distance
(`distance_dm`, decimetres), the time driven (`driven_ds`, deciseconds) and the lane holds handed out
(`lane_holds`, with `lane_holds` set).
"""

from __future__ import annotations

import time

from pydantic import Field

from gpmppi.plant.calibration_drive import CalibrationDrive, DriveConfig
from schemas import Command, State, TerrainLabel
from services.codec.convert import state_to_array
from services.runtime.node import Node
from services.runtime.node_settings import NodeSettings


class Settings(NodeSettings, DriveConfig):
    """The calibration service's settings: how it joins (here) and the drive (`DriveConfig`'s fields, top level)."""

    service: str = Field("calibrate", description="service name")
    ground: str = Field(min_length=1, description="name of the ground driven on, published as the terrain label")
    max_state_age_s: float = Field(
        0.3, gt=0, description="publish nothing on a state older than this by this host's clock [s] (egress's "
        "watchdog then stops the robot)"
    )

    def drive_config(self) -> DriveConfig:
        return DriveConfig(**{name: getattr(self, name) for name in DriveConfig.model_fields})


def run(settings: Settings) -> int:
    with Node(settings) as node:
        return serve(node, settings)


def serve(node: Node, settings: Settings) -> int:
    drive = CalibrationDrive(settings.drive_config())
    states = node.subscribe("state")
    cmd_pub = node.publisher("cmd")
    label_pub = node.publisher("terrain_label")
    node.log.info("calibration drive on %s: %g m area, up to %g m/s, target %s", settings.ground, settings.area_m,
                  settings.v_max, " or ".join(t for t in (
                      f"{settings.distance_m:g} m" if settings.distance_m else "",
                      f"{settings.duration_s:g} s" if settings.duration_s else "") if t))
    was_done = False
    while node.ok():
        state: State | None = states.take()
        if state is None:
            node.spin_once()
            continue
        stamp = state.header.stamp_ns
        age_s = (time.time_ns() - stamp) / 1e9
        if age_s > settings.max_state_age_s:
            node.counters.count("state_stale")
            node.reject(f"state is {age_s:.3f} s old (limit {settings.max_state_age_s} s): no command")
            continue
        command = drive.on_state(state_to_array(state), stamp)
        # stamped with the state's stamp, as the planner's: egress's command-age check and the log pairing read it
        cmd = Command(v_ref=float(command[0]), omega_ref=float(command[1]), source=node.zid)
        cmd.header.stamp_ns = stamp
        cmd_pub.put(cmd)
        label = TerrainLabel(terrain=settings.ground)
        label.header.stamp_ns = stamp
        label_pub.put(label)
        node.cycle()
        c = node.counters
        with c.lock:
            c.counts.update({"distance_dm": int(drive.distance * 10), "driven_ds": int(drive.elapsed * 10),
                             "lane_holds": drive.lane_holds})
            c.flags.update({"target_reached": drive.reached, "done": drive.done})
        if drive.done and not was_done:
            node.log.info("calibration drive done: %.1f m in %.1f s, %d lane holds", drive.distance, drive.elapsed,
                          drive.lane_holds)
            node.heartbeat()  # at once: the launcher ends the run on it
            was_done = True
    return 0
