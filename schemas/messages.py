"""Pydantic v2 message models.

Every message carries a `Header`; every float field rejects NaN and infinity
(`allow_inf_nan=False`), so a non-finite number never crosses a process boundary.
Units are SI, angles in radians wrapped to (-pi, pi], stamps in integer nanoseconds.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

# 2: `Command.source`, the publishing process's identity. A version-1 message (no such field) still decodes.
# 3: `TerrainWeights.unknown` and `unknown_active`, "none of the trained grounds". Older messages still decode (they
#    read as known ground: unknown 0, not active).
# 4: `Plan.model_version` (the robot profile's version planned with), and the `GroundLearn` and `ModelUpdate`
#    messages (learning a new ground online). Older plans still decode (model version 0).
# 5: `TerrainWeights.unknown_channel`, which channel of the novelty test gives `unknown`. Older messages still decode
#    (they read as not said: '').
# 6: `TerrainWeights.identified`, whether the weights name a top ground (an estimator that names none until the
#    evidence establishes one). Older messages still decode (they read as named: their top is the weights' argmax).
SCHEMA_VERSION = 6
READABLE_VERSIONS = (1, 2, 3, 4, 5, 6)

Vec2 = Annotated[list[float], Field(min_length=2, max_length=2)]


class Strict(BaseModel):
    """Base for every model here: no unknown fields, no NaN or infinity."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class Header(Strict):
    stamp_ns: int = Field(0, ge=0, description="time of validity, integer nanoseconds")
    frame_id: str = Field("map", description="coordinate frame of the pose fields")
    seq: int = Field(0, ge=0, description="per-publisher sequence number")
    schema_version: int = Field(SCHEMA_VERSION, description="message schema version")

    @model_validator(mode="after")
    def _known_version(self) -> Header:
        if self.schema_version not in READABLE_VERSIONS:
            raise ValueError(
                f"schema_version {self.schema_version} is not supported (this build speaks "
                f"{SCHEMA_VERSION} and reads {', '.join(map(str, READABLE_VERSIONS))}); upgrade the older side"
            )
        return self


class Message(Strict):
    header: Header = Field(default_factory=Header)


class State(Message):
    """Estimated robot state: pose in `header.frame_id`, body-frame velocities."""

    x: float = Field(description="position x [m]")
    y: float = Field(description="position y [m]")
    theta: float = Field(description="yaw [rad], counter-clockwise from x")
    v: float = Field(description="body-frame forward velocity [m/s]")
    omega: float = Field(description="body-frame yaw rate [rad/s]")
    covariance: list[float] | None = Field(
        None,
        min_length=25,
        max_length=25,
        description="row-major 5x5 covariance of [x, y, theta, v, omega], if known",
    )

    def as_array(self) -> list[float]:
        return [self.x, self.y, self.theta, self.v, self.omega]


class Command(Message):
    """Velocity command from the planner (or an excitation source) to the base."""

    v_ref: float = Field(description="commanded forward velocity [m/s]")
    omega_ref: float = Field(description="commanded yaw rate [rad/s]")
    source: str = Field(
        "", max_length=64, description="the publishing process's identity (its Zenoh session id; schema 2): "
        "commands from two processes tell apart, e.g. a planner and the spare that took over from it"
    )

    @model_validator(mode="after")
    def _source_since_2(self) -> Command:
        if self.source and self.header.schema_version < 2:
            raise ValueError("source is a schema_version 2 field; this message says version 1")
        return self


class BaseCommand(Message):
    """What egress sends to the base after limits and the watchdog."""

    v: float = Field(description="forward velocity [m/s]")
    omega: float = Field(description="yaw rate [rad/s]")
    reason: Literal["planner", "ramp", "watchdog", "estop", "limit", "stale_command", "estop_heartbeat"] = Field(
        "planner", description="why this command has this value: planner (as commanded), ramp (on its way to a new "
        "command, egress's command_ramp_s), limit (velocity, "
        "acceleration or jerk limited), watchdog (no command within the timeout: zero), stale_command (commands "
        "arrive but their stamps are too old: zero), estop (engaged: zero), estop_heartbeat (the e-stop source "
        "went silent: zero)"
    )


class TerrainLabel(Message):
    """Ground-truth terrain under the robot (datasets and simulation only)."""

    terrain: str = Field(min_length=1, description="terrain name, as in the terrain file")


class TerrainWeights(Message):
    """Which mixture of the trained grounds is under the robot, and whether none of them is (schema 3), which
    channel of the test says so (schema 5), and whether the weights name a top ground yet (schema 6)."""

    names: list[str] = Field(min_length=1, description="terrain names, model order")
    weights: list[float] = Field(min_length=1, description="convex weights, same order as names")
    solver_ok: bool = Field(True, description="False when the last solve failed and weights were kept")
    residual: float = Field(0.0, ge=0.0, description="objective value of the last solve")
    unknown: float = Field(
        0.0, ge=0.0, le=1.0, description="probability that the ground under the robot is none of `names` (the "
        "recent velocity residuals fit no trained ground as well as they did on held-out training drives; "
        "gpmppi/terrain/novelty.py); 0 where not assessed (before enough steps, schema 1-2 messages) [probability]")
    unknown_active: bool = Field(
        False, description="the ground is taken as unknown: set once `unknown` exceeds the enter level, cleared once "
        "it falls below the exit level (hysteresis, so it does not flicker); the planner's caution follows it")
    unknown_channel: Literal["", "one-step", "free-run"] = Field(
        "", description="which channel of the novelty test gives `unknown` (the larger of the two): 'one-step' (the "
        "one-step velocity residuals: a ground that drags or turns otherwise than any trained one), 'free-run' (each "
        "trained ground's velocity response run free for a second: a loss of grip, a slide); '' where not assessed "
        "(before a whole window is scored, no novelty test, schema 1-4 messages) (schema 5)")
    identified: bool = Field(
        True, description="whether the weights name a top ground (the largest weight): False while the evidence has "
        "established none (the estimator's `first_top: established` before its first identification; the weights "
        "are then the posterior as it is, and their largest is no identification); True in schema 1-5 messages "
        "(schema 6)")

    @model_validator(mode="after")
    def _on_simplex(self) -> TerrainWeights:
        if len(self.names) != len(self.weights):
            raise ValueError(f"{len(self.names)} names but {len(self.weights)} weights")
        if any(w < -1e-6 or w > 1 + 1e-6 for w in self.weights) or abs(sum(self.weights) - 1) > 1e-3:
            raise ValueError(f"weights {self.weights} are not on the simplex (each in [0, 1], sum 1)")
        if (self.unknown > 0.0 or self.unknown_active) and self.header.schema_version < 3:
            raise ValueError("unknown and unknown_active are schema_version 3 fields; this message says version "
                             f"{self.header.schema_version}")
        if self.unknown_channel and self.header.schema_version < 5:
            raise ValueError("unknown_channel is a schema_version 5 field; this message says version "
                             f"{self.header.schema_version}")
        if not self.identified and self.header.schema_version < 6:
            raise ValueError("identified is a schema_version 6 field; this message says version "
                             f"{self.header.schema_version}")
        return self


class GroundLearn(Message):
    """Learn the ground under the robot as a new ground of the robot profile (the terrain service, gpmppi/gp/
    online_ground.py), or stop learning it."""

    name: str = Field("", max_length=64, pattern=r"^[A-Za-z0-9_-]*$", description="the new ground's name: letters, "
                      "digits, '_' and '-' ('' : the next free new-1, new-2, ...)")
    action: Literal["start", "cancel"] = Field("start", description="start collecting its steps, or drop them")


class ModelUpdate(Message):
    """A new robot profile on disk (a ground was learned): the planner loads it between plans."""

    version: int = Field(ge=0, description="the model version: how many grounds were learned into the profile online "
                         "(0: as `gpmppi train` wrote it; kept in the profile, so it counts on across restarts)")
    path: str = Field(min_length=1, description="the profile file (.npz), as the terrain service saved it")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$", description="sha256 of the file's bytes (a reader checks it)")
    grounds: list[str] = Field(min_length=1, description="the profile's grounds, model order")
    learned: str = Field("", description="the ground this version added")
    samples: int = Field(0, ge=0, description="steps it was learned from")
    message: str = Field("", description="what the fit did, in words")


class Circle(Strict):
    x: float
    y: float
    r: float = Field(gt=0, description="radius [m]")


class Task(Message):
    """What the planner is asked to do: follow a lane, or reach a goal among obstacles."""

    kind: Literal["lane", "goal"]
    centerline: list[Vec2] = Field(default_factory=list, description="lane centre polyline [m]")
    closed: bool = Field(True, description="lane polyline is a loop")
    half_width: float = Field(1.75, gt=0, description="lane half-width [m]")
    speed_target: float = Field(1.75, ge=0, description="desired forward speed [m/s]")
    goal: Vec2 | None = Field(None, description="goal position [m]")
    goal_tolerance: float = Field(0.5, gt=0, description="goal reached within this distance [m]")
    obstacles: list[Circle] = Field(default_factory=list)

    @model_validator(mode="after")
    def _complete(self) -> Task:
        needs, problem = _TASK_NEEDS[self.kind]
        if not needs(self):
            raise ValueError(problem)
        return self


# the fields each kind of task message needs, by its `kind` (a message-level check of its own fields: the core's
# kinds check the rest when the task is converted, `services/codec/convert.py`)
_TASK_NEEDS: dict[str, tuple[Callable[[Task], bool], str]] = {
    "lane": (lambda t: len(t.centerline) >= 2, "a lane task needs a centerline of at least 2 points"),
    "goal": (lambda t: t.goal is not None, "a goal task needs a goal"),
}


class OccupancyGrid(Message):
    """Obstacles as a grid, as nav_msgs/OccupancyGrid holds them: `data` row-major from the origin cell (row 0 is the
    row at the origin, column 0 the column at it), in `header.frame_id` (the planner takes only grids in its
    odometry's frame)."""

    resolution: float = Field(gt=0, description="cell edge [m/cell]")
    width: int = Field(ge=1, le=1 << 14, description="cells per row (along the grid's x axis)")
    height: int = Field(ge=1, le=1 << 14, description="rows (along the grid's y axis)")
    origin_x: float = Field(0.0, description="x of cell (0, 0)'s outer corner in header.frame_id [m]")
    origin_y: float = Field(0.0, description="y of cell (0, 0)'s outer corner [m]")
    origin_yaw: float = Field(0.0, description="yaw of the grid's x axis in header.frame_id [rad]")
    lethal: int = Field(100, ge=1, le=255, description="values >= this are obstacles: 100 for nav_msgs occupancy, "
                        "253 for a costmap_2d's inscribed and lethal costs")
    data: list[Annotated[int, Field(ge=-128, le=255)]] = Field(
        description="width x height cell values, row-major: 0 free .. lethal and above an obstacle, negative "
        "unknown (nav_msgs' int8 -1)")

    @model_validator(mode="after")
    def _sized(self) -> OccupancyGrid:
        if len(self.data) != self.width * self.height:
            raise ValueError(f"data has {len(self.data)} values for a grid of width {self.width} x height "
                             f"{self.height} = {self.width * self.height}; send width x height values, row-major")
        return self


class Plan(Message):
    """The planner's output for one cycle, for logging and visualization."""

    command: Command
    controls: list[Vec2] = Field(description="optimal control sequence, N x [v_ref, omega_ref]")
    states: list[list[float]] = Field(description="nominal trajectory, (N+1) x [x, y, theta, v, omega]")
    cov_xy: list[list[float]] = Field(
        default_factory=list, description="(N+1) x [sxx, sxy, syy] position covariance"
    )
    tightened: list[float] = Field(
        default_factory=list,
        description="per step: tightened lane half-width, or obstacle inflation [m]",
    )
    samples: list[list[Vec2]] = Field(default_factory=list, description="subset of rollouts, XY only")
    sample_costs: list[float] = Field(default_factory=list)
    terrain_weights: list[float] = Field(default_factory=list)
    weights_stale: bool = Field(False, description="the terrain weights planned with are older than the limit")
    model_version: int = Field(0, ge=0, description="the robot profile's version planned with (`ModelUpdate.version`: "
                               "grounds learned into it online; 0: none)")
    timings_ms: dict[str, float] = Field(default_factory=dict)
    critic_costs: dict[str, float] = Field(
        default_factory=dict,
        description="each critic's cost of the nominal sequence, by critic name (variance, deviation, slip, "
        "lane_exit, speed, collision, costmap, goal, terminal); they sum to the nominal sequence's cost [cost]",
    )
    effective_samples: float | None = Field(
        None,
        description="effective sample size of the update, 1 / sum of the squared normalised rollout weights: "
        "1 when one rollout decides it, the sample count when all weigh the same, 0 when none was finite; "
        "None in recordings made before it was reported [samples]",
    )

    @model_validator(mode="after")
    def _versioned(self) -> Plan:
        if self.model_version > 0 and self.header.schema_version < 4:
            raise ValueError(f"model_version is a schema_version 4 field; this message says version "
                             f"{self.header.schema_version}")
        return self


class Heartbeat(Message):
    """A service's health, once a second on `gpmppi/{robot}/health/{service}`."""

    service: str = Field(description="service name")
    rate_hz: float = Field(0.0, ge=0, description="main-work cycles per second over the last 2 s [Hz]")
    received: int = Field(0, ge=0, description="messages received since start")
    rejected: int = Field(0, ge=0, description="messages rejected since start (bad payload, stale, out of range)")
    published: int = Field(0, ge=0, description="messages published since start")
    last_error: str = Field("", description="the most recent error or rejection, in words")
    status: Literal["ok", "degraded", "failing"] = Field(
        "ok", description="ok; degraded (working on fallbacks, e.g. stale inputs); failing (main work not done)"
    )
    counts: dict[str, int] = Field(default_factory=dict, description="service-specific named counters")
    flags: dict[str, bool] = Field(default_factory=dict, description="service-specific named conditions")


class EStop(Message):
    engaged: bool
    reason: str = ""


# Every top-level message model by class name (schema registry for files and tools).
MODELS: dict[str, type[Message]] = {
    m.__name__: m
    for m in (State, Command, BaseCommand, TerrainLabel, TerrainWeights, Task, OccupancyGrid, Plan, Heartbeat, EStop,
              GroundLearn, ModelUpdate)
}
