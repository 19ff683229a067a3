"""The one message -> Foxglove scene mapping, shared by the live `foxglove` service, the recorder's scene channels
and `gpmppi replay --foxglove-scene` (a recording's scene added offline).

It draws what `services.view.geometry` computes (the same geometry, colours and decimation as the rerun view) and
only translates it into Foxglove's own schemas (protobuf, `foxglove.*`), so Foxglove's 3D panel shows it with
nothing converted. Per robot, on topics outside `gpmppi/**` (they are views, never Zenoh keys):

- `scene/<robot>/tf` (foxglove.FrameTransforms): map -> base_link, from each state;
- `scene/<robot>/pose` (foxglove.PoseInFrame): the robot's pose in map;
- `scene/<robot>/robot` (foxglove.SceneUpdate): the robot's footprint, the driven path (in strips: only the growing
  one is sent);
- `scene/<robot>/task` (foxglove.SceneUpdate): lane edges and centre, or obstacles and goal, with each task message;
  a costmap's lethal cells (cubes), with each grid message;
- `scene/<robot>/plan` (foxglove.SceneUpdate): the nominal plan, its covariance ellipses, the tightened lane bounds
  or the inflated obstacles, and the rollouts coloured by cost rank;
- `scene/<robot>/events` (foxglove.Log): e-stop, safety overrides, task changes, service status.

Lines lie in the ground plane, lifted by their layer's draw order (1 mm per step) so the layers stack as in rerun.

What is mapped is what is read: `map(..., wanted=...)` makes only the scene topics named (the live server names those
a client subscribes to; the recorder all), and `scene_feeds(key)` says which scene topics a key's messages feed, so a
key that feeds nothing anyone reads is never decoded. The plan's scene (its heaviest part: ellipses, tightened
bounds, rollouts) is drawn at most `plan_hz` times a second of message time, live and recorded alike.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from gpmppi.tasks import TaskOutline
from schemas import BaseCommand, EStop, Heartbeat, Message, OccupancyGrid, Plan, State, Task, model_for_key
from services.codec.convert import task_from_message
from services.view import geometry as geo

if TYPE_CHECKING:
    import foxglove

SCENE_PREFIX = "scene/"
MAP_FRAME = "map"
# where a plan's bounds are drawn, by their layer (`geometry.plan_bounds`)
_BOUND_ENTITIES = {"tightened": "lane/tightened", "inflated": "obstacles/inflated"}
BASE_FRAME = "base_link"
# topic (after scene/<robot>/) -> the Foxglove schema of its messages
SCENE_SCHEMAS = {
    "tf": "FrameTransforms",
    "pose": "PoseInFrame",
    "robot": "SceneUpdate",
    "task": "SceneUpdate",
    "plan": "SceneUpdate",
    "events": "Log",
}


# which scene topics (names as in SCENE_SCHEMAS) each message model feeds; a model not named feeds none. The task feeds
# the plan too: the tightened lane bounds and the inflated obstacles are drawn from it.
_FEEDS: dict[type[Message], frozenset[str]] = {
    State: frozenset({"tf", "pose", "robot"}),
    Plan: frozenset({"plan"}),
    Task: frozenset({"task", "plan", "events"}),
    OccupancyGrid: frozenset({"task"}),
    EStop: frozenset({"events"}),
    BaseCommand: frozenset({"events"}),
    Heartbeat: frozenset({"events"}),
}


def scene_feeds(key: str) -> frozenset[str]:
    """The scene topics (names after `scene/<robot>/`) that messages on `key` feed: a key none of whose topics is
    read need not be decoded for the scene. Only the estimated state (`.../state`) draws the robot, not the raw
    odometry."""
    try:
        model = model_for_key(key)
    except KeyError:
        return frozenset()
    if model is State and not key.endswith("/state"):
        return frozenset()
    return _FEEDS.get(model, frozenset())


@dataclass
class SceneOptions(geo.Decimation):
    """The shared decimation (`geometry.Decimation`, as rerun's) and what only the Foxglove scene bounds."""

    plan_hz: float = 5.0  # draw the plan's scene (nominal, ellipses, bounds, rollouts) at most this often [1/s]
    samples_every: int = 1  # the rollouts of every drawn plan: plan_hz bounds them already (rerun's 5 Hz at 10 Hz)


class RateLimit:
    """At most `hz` accepted stamps a second, on a grid of 1/hz from the first: a stamp is accepted from a quarter
    period before its slot on (so a 10 Hz stream with jitter halves evenly to 5 Hz), and the grid restarts after a
    gap of a period or a stamp that goes back (a new run, a replay looped). Over any span T [s] at most
    T * hz + 2 are accepted; `hz` <= 0 accepts every stamp."""

    def __init__(self, hz: float) -> None:
        self.period_ns = int(1e9 / hz) if hz > 0 else 0
        self._due: int | None = None

    def __call__(self, stamp_ns: int) -> bool:
        if self.period_ns == 0:
            return True
        due = self._due
        if due is None or stamp_ns < due - 2 * self.period_ns or stamp_ns >= due + self.period_ns:
            self._due = stamp_ns + self.period_ns
            return True
        if stamp_ns >= due - self.period_ns // 4:
            self._due = due + self.period_ns
            return True
        return False


def scene_topic(robot: str, name: str) -> str:
    return f"{SCENE_PREFIX}{robot}/{name}"


def is_scene_topic(topic: str) -> bool:
    return topic.startswith(SCENE_PREFIX)


def scene_topics(robot: str) -> list[str]:
    """Every scene topic of one robot."""
    return [scene_topic(robot, name) for name in SCENE_SCHEMAS]


def schema_of(topic: str) -> foxglove.Schema:
    """The Foxglove schema (protobuf) of a scene topic."""
    from foxglove import messages

    return getattr(messages, SCENE_SCHEMAS[topic.rsplit("/", 1)[-1]]).get_schema()


@dataclass(frozen=True)
class SceneMessage:
    """One encoded scene message: its topic, the Foxglove schema name, protobuf bytes, and its time [ns]."""

    topic: str
    schema: str
    data: bytes
    stamp_ns: int


def robot_of(key: str) -> str:
    """The robot a `gpmppi/<robot>/...` key belongs to."""
    parts = key.split("/")
    return parts[1] if len(parts) >= 3 and parts[0] == "gpmppi" else "robot"


class FoxgloveSceneMapper:
    """Maps gpmppi messages to Foxglove scene messages: `map(key, msg, fallback_ns)` returns what to send."""

    def __init__(self, options: geo.Decimation | None = None) -> None:
        from foxglove import messages as fm
        from foxglove.messages import Duration, Timestamp

        self.fm = fm
        self._timestamp = Timestamp
        self._forever = Duration(0, 0)
        self.opt = options or SceneOptions()
        self.plan_hz = self.opt.plan_hz if isinstance(self.opt, SceneOptions) else SceneOptions.plan_hz
        self._plan_rate: dict[str, RateLimit] = {}
        self.task: dict[str, Task] = {}
        self.outline: dict[str, TaskOutline] = {}  # what each robot's task's kind outlines (`Task.outline`)
        self._paths: dict[str, geo.PathStrips] = {}
        self._plans: dict[str, int] = {}
        self._plan_seq: dict[str, int] = {}
        self._estop: dict[str, bool] = {}
        self._reason: dict[str, str] = {}
        self._status: dict[tuple[str, str], str] = {}

    # ---- translation helpers ----------------------------------------------------------------------------------
    def _ts(self, stamp_ns: int) -> Any:
        return self._timestamp(int(stamp_ns) // 1_000_000_000, int(stamp_ns) % 1_000_000_000)

    def _color(self, rgba: Sequence[int] | np.ndarray) -> Any:
        c = [float(v) / 255.0 for v in rgba]
        return self.fm.Color(r=c[0], g=c[1], b=c[2], a=c[3] if len(c) > 3 else 1.0)

    def _line(self, points: np.ndarray, layer: str, color: Sequence[int] | np.ndarray | None = None) -> Any:
        style = geo.LAYERS[layer]
        z = style.order / 1000.0
        point = self.fm.Point3  # the list of floats first: a numpy scalar per coordinate costs as much as the point
        pts = [point(x=x, y=y, z=z) for x, y in np.asarray(points, dtype=np.float64)[:, :2].tolist()]
        rgba = color if color is not None else style.color
        assert rgba is not None and style.radius is not None
        return self.fm.LinePrimitive(
            type=self.fm.LinePrimitiveLineType.LineStrip,
            thickness=2.0 * style.radius,
            scale_invariant=False,
            points=pts,
            color=self._color(rgba),
        )

    def _entity(self, entity_id: str, stamp_ns: int, **primitives: Any) -> Any:
        return self.fm.SceneEntity(
            timestamp=self._ts(stamp_ns), frame_id=MAP_FRAME, id=entity_id, lifetime=self._forever, **primitives
        )

    def _update(self, topic: str, stamp_ns: int, entities: list[Any], deletions: list[str] = ()) -> SceneMessage:
        dels = [
            self.fm.SceneEntityDeletion(
                timestamp=self._ts(stamp_ns), type=self.fm.SceneEntityDeletionType.MatchingId, id=i
            )
            for i in deletions
        ]
        msg = self.fm.SceneUpdate(deletions=dels, entities=entities)
        return SceneMessage(topic, "foxglove.SceneUpdate", msg.encode(), stamp_ns)

    def _log(self, robot: str, stamp_ns: int, text: str, level: str = "Info") -> SceneMessage:
        msg = self.fm.Log(
            timestamp=self._ts(stamp_ns), level=getattr(self.fm.LogLevel, level), message=text, name="gpmppi"
        )
        return SceneMessage(scene_topic(robot, "events"), "foxglove.Log", msg.encode(), stamp_ns)

    # ---- messages ---------------------------------------------------------------------------------------------
    def map(
        self, key: str, msg: Message, fallback_ns: int, wanted: Collection[str] | None = None
    ) -> list[SceneMessage]:
        """The scene messages for one message received on `key` (`fallback_ns` when its header has no stamp): only
        those on the scene topics named in `wanted` (names after `scene/<robot>/`; None: every topic). A topic left
        out costs nothing and keeps no state (a driven path, a plan count), as if its messages had not come."""
        t = msg.header.stamp_ns or fallback_ns
        robot = robot_of(key)
        if wanted is None:
            wanted = SCENE_SCHEMAS
        if isinstance(msg, State):
            return self._state(robot, msg, t, wanted) if key.endswith("/state") else []
        if isinstance(msg, Plan):
            return self._plan(robot, msg, t) if "plan" in wanted else []
        if isinstance(msg, Task):
            return self._task(robot, msg, t, wanted)
        if isinstance(msg, OccupancyGrid):
            return self._costmap(robot, msg, t) if "task" in wanted else []
        if "events" not in wanted:
            return []
        if isinstance(msg, EStop):
            if msg.engaged != self._estop.get(robot):
                self._estop[robot] = msg.engaged
                text = f"e-stop {'engaged' if msg.engaged else 'released'}{': ' + msg.reason if msg.reason else ''}"
                return [self._log(robot, t, text, "Warning" if msg.engaged else "Info")]
        if isinstance(msg, BaseCommand):
            reason = msg.reason if msg.reason in ("watchdog", "estop") else "planner"
            previous = self._reason.get(robot)
            self._reason[robot] = reason
            if reason != previous and (previous is not None or reason != "planner"):
                text = f"egress: {reason} override" if reason != "planner" else f"egress: {previous} override ended"
                return [self._log(robot, t, text, "Warning" if reason != "planner" else "Info")]
        if isinstance(msg, Heartbeat):
            previous = self._status.get((robot, msg.service))
            self._status[(robot, msg.service)] = msg.status
            if msg.status != previous:
                level = {"ok": "Info", "degraded": "Warning", "failing": "Error"}[msg.status]
                text = f"{msg.service}: {'up' if previous is None else 'status ' + previous + ' ->'} {msg.status}"
                return [self._log(robot, t, text, level)]
        return []

    def _state(self, robot: str, msg: State, t: int, wanted: Collection[str]) -> list[SceneMessage]:
        fm = self.fm
        half = msg.theta / 2.0
        rotation = fm.Quaternion(x=0.0, y=0.0, z=float(np.sin(half)), w=float(np.cos(half)))
        out = []
        if "tf" in wanted:
            out.append(self._tf(robot, msg, t, rotation))
        if "pose" in wanted:
            pose = fm.PoseInFrame(
                timestamp=self._ts(t),
                frame_id=MAP_FRAME,
                pose=fm.Pose(position=fm.Vector3(x=msg.x, y=msg.y, z=0.0), orientation=rotation),
            )
            out.append(SceneMessage(scene_topic(robot, "pose"), "foxglove.PoseInFrame", pose.encode(), t))
        if "robot" in wanted:
            path = self._paths.setdefault(robot, geo.PathStrips(self.opt.path_chunk))
            index, points = path.add(msg.x, msg.y)
            outline = geo.robot_outline(msg.x, msg.y, msg.theta)
            entities = [self._entity("robot", t, lines=[self._line(outline, "robot")])]
            if len(points) >= 2:
                strip = self._line(np.asarray(points), "path")
                entities.append(self._entity(f"driven_path/{index:05d}", t, lines=[strip]))
            out.append(self._update(scene_topic(robot, "robot"), t, entities))
        return out

    def _tf(self, robot: str, msg: State, t: int, rotation: Any) -> SceneMessage:
        fm = self.fm
        tf = fm.FrameTransforms(
            transforms=[
                fm.FrameTransform(
                    timestamp=self._ts(t),
                    parent_frame_id=MAP_FRAME,
                    child_frame_id=BASE_FRAME,
                    translation=fm.Vector3(x=msg.x, y=msg.y, z=0.0),
                    rotation=rotation,
                )
            ]
        )
        return SceneMessage(scene_topic(robot, "tf"), "foxglove.FrameTransforms", tf.encode(), t)

    def _costmap(self, robot: str, msg: OccupancyGrid, t: int) -> list[SceneMessage]:
        """A grid's lethal cells as flat cubes on the task's topic (sent with every grid message, as the task is)."""
        centres, half = geo.lethal_cells(msg)
        style = geo.LAYERS["costmap"]
        q = self.fm.Quaternion(x=0.0, y=0.0, z=float(np.sin(msg.origin_yaw / 2)), w=float(np.cos(msg.origin_yaw / 2)))
        cubes = [
            self.fm.CubePrimitive(
                pose=self.fm.Pose(position=self.fm.Vector3(x=float(x), y=float(y), z=0.05), orientation=q),
                size=self.fm.Vector3(x=2 * half, y=2 * half, z=0.1),
                color=self._color(style.color or (200, 40, 40)),
            )
            for x, y in centres
        ]
        return [self._update(scene_topic(robot, "task"), t, [self._entity("costmap", t, cubes=cubes)])]

    def _task(self, robot: str, msg: Task, t: int, wanted: Collection[str]) -> list[SceneMessage]:
        previous = self.task.get(robot)
        changed = previous is None or previous.model_dump(exclude={"header"}) != msg.model_dump(exclude={"header"})
        self.task[robot] = msg  # kept whatever is read: the plan's bounds are drawn from it
        if changed:
            try:
                self.outline[robot] = task_from_message(msg).outline()
            except ValueError:  # the message validated, but the core's task refuses it: nothing to draw
                self.outline.pop(robot, None)
        if "task" not in wanted and "events" not in wanted:
            return []
        # sent with every task message (the planner re-publishes it once a second), so a client that connects late,
        # or a recording opened in the middle, shows the map within a second
        outline = self.outline.get(robot)
        if outline is None:
            return [self._log(robot, t, "task not drawn: the planner's core refuses it", "Warning")] if changed and \
                "events" in wanted else []
        drawn = geo.task_lines(outline)
        entities = [self._entity(entity, t, lines=[self._line(line, layer) for line in lines])
                    for entity, (layer, lines) in drawn.items()]
        if outline.circles.shape[0]:
            style = geo.LAYERS["obstacles"]
            cylinders = [
                self.fm.CylinderPrimitive(
                    pose=self.fm.Pose(
                        position=self.fm.Vector3(x=x, y=y, z=0.1),
                        orientation=self.fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                    ),
                    size=self.fm.Vector3(x=2 * r, y=2 * r, z=0.2),
                    bottom_scale=1.0,
                    top_scale=1.0,
                    color=self._color(style.color or (200, 40, 40)),
                )
                for x, y, r in outline.circles.tolist()
            ]
            entities.append(self._entity("obstacles", t, cylinders=cylinders))
        drawn_ids = set(drawn) | ({"obstacles"} if outline.circles.shape[0] else set())
        gone = [e for e in geo.TASK_ENTITIES if e not in drawn_ids]  # what an earlier task of another kind drew
        text = "task: " + outline.summary
        out = (
            [self._update(scene_topic(robot, "task"), t, entities, gone if changed else [])] if "task" in wanted else []
        )
        if changed and "events" in wanted:
            out.append(self._log(robot, t, text if previous is None else "task changed: " + text))
        return out

    def _plan(self, robot: str, msg: Plan, t: int) -> list[SceneMessage]:
        if msg.header.seq < self._plan_seq.get(robot, -1):  # a new planner process counts from 0 again
            self._plans[robot] = 0
        self._plan_seq[robot] = msg.header.seq
        if not self._plan_rate.setdefault(robot, RateLimit(self.plan_hz))(t):
            return []
        plans = self._plans[robot] = self._plans.get(robot, 0) + 1
        entities = []
        states = geo.plan_states(msg)
        if states is not None:
            entities.append(self._entity("plan/nominal", t, lines=[self._line(states, "nominal")]))
            ellipses = geo.plan_ellipses(msg, states, self.opt.ellipse_every)
            if ellipses is not None:
                lines = [self._line(e, "covariance") for e in ellipses]
                entities.append(self._entity("plan/covariance", t, lines=lines))
            outline = self.outline.get(robot)
            if msg.tightened and outline is not None:
                # the bounds as the task's kind says what they are: a lane's tightened half-widths, the circles'
                # inflation
                layer, lines = geo.plan_bounds(msg, states, outline)
                entities.append(self._entity(_BOUND_ENTITIES[layer], t, lines=[self._line(b, layer) for b in lines]))
        if (plans - 1) % self.opt.samples_every == 0:
            drawn = geo.rollouts(msg, self.opt.max_samples, self.opt.sample_stride)
            if drawn is not None:
                points, colors = drawn
                lines = [self._line(p, "samples", c) for p, c in zip(points, colors, strict=True)]
                entities.append(self._entity("plan/rollouts", t, lines=lines))
        return [self._update(scene_topic(robot, "plan"), t, entities)] if entities else []
