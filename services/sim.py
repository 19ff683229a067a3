"""sim: the simulated robot. Steps the physics plant in real time with the newest `base/cmd`,
publishes the measured state on `odom/raw` at `publish_hz` and the true terrain on `terrain/label`; its
`terrain_switches` change the ground mid-run (new ground in a running stack: docs/new_ground.md)."""

from __future__ import annotations

import time

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from schemas import TerrainLabel
from services.codec.convert import state_from_array
from services.runtime.node import Node
from services.runtime.node_settings import NodeSettings


class TerrainSwitch(BaseModel):
    model_config = ConfigDict(extra="forbid")
    # from the first moving command, not the sim's start: a planner that compiles its kernels on a cold start takes
    # tens of seconds, and a switch timed from the start would then come before the robot drives at all
    at_s: float = Field(ge=0, allow_inf_nan=False, description="time from the first command that moves the robot [s]")
    terrain: str = Field(description="the ground from then on (a name in the terrain file)")


class Settings(NodeSettings):
    service: str = Field("sim", description="service name")
    terrain: str = Field("asphalt", description="terrain under the robot (a name in the terrain file)")
    terrain_file: str | None = Field(None, description="terrain set YAML (None: the shipped one)")
    start: list[float] | None = Field(
        None, min_length=5, max_length=5, description="initial [X, Y, theta, v, omega] (None: the lane's start)"
    )
    lane: str = Field("circle", description="lane whose start pose is used when `start` is None")
    step_hz: float = Field(100.0, gt=0, description="plant stepping rate (commands take effect at this rate) [Hz]")
    publish_hz: float = Field(10.0, gt=0, description="odom/raw publication rate [Hz]")
    seed: int = Field(0, description="sensor-noise seed")
    noise: bool = Field(True, description="add sensor noise to the published state")
    command_timeout_s: float = Field(
        0.25, gt=0, description="apply zero when base/cmd is older than this [s] (the base's own safety; the "
        "Jackal's ROS 1 cmd_vel_timeout; egress repeats its output at rate_hz, well inside it)"
    )
    frame_id: str = Field("odom", description="frame of the published pose")
    terrain_switches: list[TerrainSwitch] = Field(
        default_factory=list, description="the ground changes mid-run, in time order: `at_s` after the first "
        "command that moves the robot the plant's ground becomes `terrain` (a name in the terrain file; it may be one "
        "the robot profile lacks: new ground is what it is for)"
    )

    @field_validator("terrain_switches")
    @classmethod
    def _switches_known(cls, switches: list[TerrainSwitch], info: ValidationInfo) -> list[TerrainSwitch]:
        # checked against the terrain set when the launch file is read, not at the switch, minutes into a run
        if not switches:
            return switches
        times = [s.at_s for s in switches]
        if times != sorted(times):
            raise ValueError(f"switch times {times} are not in time order; list the switches by `at_s`")
        from gpmppi.plant.terrains import load_terrains

        names = load_terrains(info.data.get("terrain_file")).names
        for s in switches:
            if s.terrain not in names:
                raise ValueError(f"switch at {s.at_s:g} s names ground {s.terrain!r}, which the terrain set lacks "
                                 f"(its grounds: {names}); name one of them or give a terrain_file that has it")
        return switches


def initial_state(settings: Settings) -> np.ndarray:
    if settings.start is not None:
        return np.asarray(settings.start, dtype=np.float64)
    from gpmppi.scenarios import lane_scenario

    return np.asarray(lane_scenario(settings.lane).start, dtype=np.float64)


def run(settings: Settings) -> int:
    from gpmppi.plant.physics import PhysicsPlant
    from gpmppi.plant.terrains import load_terrains

    plant = PhysicsPlant(
        load_terrains(settings.terrain_file), settings.terrain, seed=settings.seed, noise=settings.noise
    )
    plant.reset(initial_state(settings))
    step_dt = 1.0 / settings.step_hz
    publish_every = max(1, round(settings.step_hz / settings.publish_hz))
    with Node(settings) as node:
        odom = node.publisher("odom_raw")
        label = node.publisher("terrain_label")
        base_cmd = node.subscribe("base_cmd")
        command = np.zeros(2)
        command_time = -np.inf
        tick = 0
        next_tick = time.monotonic()
        switches = list(settings.terrain_switches)
        driving_since: float | None = None  # the schedule's clock: the first command that moves the robot
        while node.ok():
            msg = base_cmd.take()
            if msg is not None:
                command = np.array([msg.v, msg.omega])
                command_time = time.monotonic()
                if driving_since is None and np.any(command != 0.0):
                    driving_since = next_tick
            delay = next_tick - time.monotonic()
            if delay > 0.0:  # wait for the tick (a command arriving meanwhile wakes us; it applies from the tick)
                node.spin_once(delay)
                continue
            if time.monotonic() - command_time > settings.command_timeout_s:
                command = np.zeros(2)  # the base's own safety: no fresh command, no motion
            while switches and driving_since is not None and next_tick - driving_since >= switches[0].at_s:
                switch = switches.pop(0)
                node.log.info("ground switched from %r to %r, %.1f s after the first moving command (schedule)",
                              plant.terrain, switch.terrain, next_tick - driving_since)
                plant.set_terrain(switch.terrain)
            if tick % publish_every == 0:
                stamp = time.time_ns()
                measured = plant.measure()
                if np.all(np.isfinite(measured)):
                    odom.put(state_from_array(measured, stamp, settings.frame_id))
                    terrain_label = TerrainLabel(terrain=plant.terrain)
                    terrain_label.header.stamp_ns = stamp
                    label.put(terrain_label)
                    node.cycle()
                else:
                    node.error(f"plant produced a non-finite state {measured}; not published")
            plant.step(command, step_dt)
            tick += 1
            next_tick += step_dt
            if next_tick - time.monotonic() < -1.0:  # fell far behind (machine stalled): resynchronise, not race
                next_tick = time.monotonic()
            node.spin_once(0.0)
    return 0
