"""The one message -> rerun mapping, shared by the viewer service (live) and the offline converter (replay).

Everything is on one timeline, `stamp` (the header stamp; the receive or log time when a message has none).
Growth is linear in the run's length:
- styling (colours, widths, names, draw order) is logged once, static;
- time series are buffered and sent as columns (`send_columns`), one chunk per series per flush;
- the driven path is extended incrementally: the robot's positions go in short strips, one entity per
  `path_chunk` states, each strip re-logged only while it grows, so a state costs at most `path_chunk` points;
- the per-plan rollouts are decimated by `samples_every` / `max_samples`, the ellipses by `ellipse_every`.
Events (watchdog, e-stop, restarts, rejected input, status changes) go to a text log, `events`, when they change.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from gpmppi.tasks import TaskOutline
from schemas import (
    BaseCommand,
    Command,
    EStop,
    Heartbeat,
    Message,
    OccupancyGrid,
    Plan,
    State,
    Task,
    TerrainWeights,
)
from services.codec.convert import task_from_message
from services.view import geometry as geo

if TYPE_CHECKING:
    import rerun as rr

TIMELINE = "stamp"
EVENTS = "events"
# where a plan's bounds are drawn, by their layer (`geometry.plan_bounds`)
_BOUND_ENTITIES = {"tightened": "map/lane/tightened", "inflated": "map/obstacles_inflated"}

# (entity, legend name, RGB colour, line width [px]) of every fixed time series
SERIES: dict[str, tuple[str, tuple[int, int, int], float]] = {
    "plots/v/state": ("v (state)", (30, 120, 255), 2.0),
    "plots/v/cmd": ("v_ref (planner)", (255, 150, 0), 1.5),
    "plots/v/base": ("v (base cmd)", (40, 40, 40), 1.0),
    "plots/omega/state": ("omega (state)", (30, 120, 255), 2.0),
    "plots/omega/cmd": ("omega_ref (planner)", (255, 150, 0), 1.5),
    "plots/omega/base": ("omega (base cmd)", (40, 40, 40), 1.0),
    "plots/tightening/nominal": ("lane half-width", (90, 90, 90), 1.0),
    "plots/tightening/first": ("tightened, step 1", (230, 170, 0), 2.0),
    "plots/tightening/last": ("tightened, last step", (200, 90, 0), 2.0),
    "plots/cost/min": ("min rollout cost", (20, 150, 130), 2.0),
    "plots/cost/median": ("median rollout cost", (215, 50, 50), 1.5),
    "plots/terrain/unknown": ("P(unknown ground)", (20, 20, 20), 2.5),
}
PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
           (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]  # fmt: skip

# map layers, bottom to top: the draw order of each (the colours and widths are in `geometry.LAYERS`, shared)
DRAW = {name: layer.order for name, layer in geo.LAYERS.items()}


# heartbeat counters / flags that change in normal operation: egress limiting a ramp is shaping, not an event
# (the base command's reason shows it in the plots)
# and unknown ground: the terrain service's P(unknown) (the weights plot shows it) and its decision and count (the
# weights' own event says it), and the planner's caution counters (its `caution` flag is the event)
ROUTINE_HEALTH = frozenset({"limited", "unknown_permille", "unknown_ground", "unknown_free_run", "unknown_entered",
                            "caution_on", "caution_off"})
# what the unknown-ground event says of the channel that gives P(unknown) (`TerrainWeights.unknown_channel`)
_CHANNEL_SAYS = {"one-step": " by its one-step response (one-step channel)",
                 "free-run": " by its grip: the robot slides (free-run channel)"}


@dataclass
class ViewOptions(geo.Decimation):
    """How much per-plan data is drawn (`geometry.Decimation`, shared with Foxglove), and the timing plot's
    start-up cut."""

    timing_warmup_plans: int = 5  # a (re)started planner's first plans: reported as an event, not plotted


def _line(layer: str, **fields: Any) -> rr.LineStrips2D:
    """The static style of a line layer of `geometry.LAYERS` (colour, radius, draw order)."""
    import rerun as rr

    style = geo.LAYERS[layer]
    colors = {"colors": [style.color]} if style.color is not None else {}
    return rr.LineStrips2D.from_fields(**colors, radii=[style.radius], draw_order=style.order, **fields)


def _strips(strips: list) -> np.ndarray | list[np.ndarray]:
    """Strips as one float32 array when they have the same length (rerun's fast path), else a list."""
    if len({len(p) for p in strips}) == 1:
        return np.asarray(strips, dtype=np.float32)
    return [np.asarray(p, dtype=np.float32) for p in strips]


class RerunMapper:
    """Logs gpmppi messages to one rerun recording stream; `flush()` sends the buffered time series."""

    def __init__(self, rec: rr.RecordingStream, options: ViewOptions | None = None) -> None:
        self.rec = rec
        self.opt = options or ViewOptions()
        self.task: Task | None = None
        self.outline: TaskOutline | None = None  # what the task's kind outlines (`gpmppi.tasks.Task.outline`)
        self._grid_key: str | None = None  # the grid drawn (its message without the stamp)
        self._series: dict[str, tuple[list[int], list[float]]] = {}
        self._styled: set[str] = set()
        self._path = geo.PathStrips(self.opt.path_chunk)
        self._plans = 0  # plans since the planner (re)started
        self._plan_seq = -1
        self._warmup_ms: list[float] = []
        self._terrain_names: list[str] = []
        self._last_reason: str | None = None
        self._estop: bool | None = None
        self._stale: bool | None = None
        self._solver_ok: bool | None = None
        self._unknown: bool | None = None  # the terrain service's unknown_active, as last shown
        self._health: dict[str, Heartbeat] = {}
        self.buffered = 0

    # ---- time helpers ---------------------------------------------------------------------
    def _at(self, stamp_ns: int) -> None:
        self.rec.set_time(TIMELINE, timestamp=np.datetime64(int(stamp_ns), "ns"))

    def _static(self, entity: str, archetype: Any) -> None:
        if entity not in self._styled:
            self._styled.add(entity)
            self.rec.log(entity, archetype, static=True)

    def _scalar(self, entity: str, stamp_ns: int, value: float, name: str | None = None) -> None:
        import rerun as rr

        if entity not in self._styled:
            if entity in SERIES:
                label, color, width = SERIES[entity]
            else:
                label, width = name or entity.rsplit("/", 1)[-1], 1.5
                color = PALETTE[len([e for e in self._styled if e.startswith(entity.rsplit("/", 1)[0])]) % 10]
            self._static(entity, rr.SeriesLines(colors=[color], names=[label], widths=[width]))
        ts, vs = self._series.setdefault(entity, ([], []))
        ts.append(int(stamp_ns))
        vs.append(float(value))
        self.buffered += 1

    def flush(self) -> None:
        """Send the buffered time series, one column chunk per series."""
        import rerun as rr

        for entity, (ts, vs) in self._series.items():
            if ts:
                self.rec.send_columns(
                    entity,
                    indexes=[rr.TimeColumn(TIMELINE, timestamp=np.asarray(ts, dtype="datetime64[ns]"))],
                    columns=rr.Scalars.columns(scalars=np.asarray(vs, dtype=np.float64)),
                )
                ts.clear()
                vs.clear()
        self.buffered = 0

    def event(self, stamp_ns: int, text: str, level: str = "INFO") -> None:
        import rerun as rr

        self._at(stamp_ns)
        self.rec.log(EVENTS, rr.TextLog(text, level=level))

    # ---- messages -------------------------------------------------------------------------
    def log(self, key: str, msg: Message, fallback_ns: int) -> None:
        """Map one message received on `key`; `fallback_ns` is used when its header has no stamp."""
        t = msg.header.stamp_ns or fallback_ns
        if isinstance(msg, State):
            if key.endswith("/state"):  # the plant's own odometry (odom/raw) is the estimator's input, not shown
                self._state(msg, t)
        elif isinstance(msg, Plan):
            self._plan(msg, t)
        elif isinstance(msg, Command):
            self._scalar("plots/v/cmd", t, msg.v_ref)
            self._scalar("plots/omega/cmd", t, msg.omega_ref)
        elif isinstance(msg, BaseCommand):
            self._base(msg, t)
        elif isinstance(msg, TerrainWeights):
            self._weights(msg, t)
        elif isinstance(msg, Task):
            self._task(msg, t)
        elif isinstance(msg, OccupancyGrid):
            self._costmap(msg, t)
        elif isinstance(msg, Heartbeat):
            self._heartbeat(msg, t)
        elif isinstance(msg, EStop):
            if msg.engaged != self._estop:
                self._estop = msg.engaged
                state = "engaged" if msg.engaged else "released"
                self.event(
                    t, f"e-stop {state}{': ' + msg.reason if msg.reason else ''}", "WARN" if msg.engaged else "INFO"
                )

    def _state(self, msg: State, t: int) -> None:
        import rerun as rr

        self._at(t)
        self._static("map/robot", _line("robot"))
        self.rec.log(
            "map/robot", rr.LineStrips2D.from_fields(strips=_strips([geo.robot_outline(msg.x, msg.y, msg.theta)]))
        )
        # the driven path: a strip per `path_chunk` states, starting where the previous one ended
        index, points = self._path.add(msg.x, msg.y)
        entity = f"map/driven_path/{index:05d}"
        self._static(entity, _line("path"))
        if len(points) >= 2:
            self.rec.log(entity, rr.LineStrips2D.from_fields(strips=_strips([points])))
        self._scalar("plots/v/state", t, msg.v)
        self._scalar("plots/omega/state", t, msg.omega)

    def _base(self, msg: BaseCommand, t: int) -> None:
        self._scalar("plots/v/base", t, msg.v)
        self._scalar("plots/omega/base", t, msg.omega)
        # planner and limit alternate all the time (a limited planner command): events are the safety overrides
        reason = msg.reason if msg.reason in ("watchdog", "estop") else "planner"
        if reason != self._last_reason:
            if reason != "planner":
                self.event(t, f"egress: {reason} override, base command v {msg.v:.2f} omega {msg.omega:.2f}", "WARN")
            elif self._last_reason is not None:
                self.event(t, f"egress: {self._last_reason} override ended, planner commands again")
            self._last_reason = reason

    def _weights(self, msg: TerrainWeights, t: int) -> None:
        for name, w in zip(msg.names, msg.weights, strict=True):
            self._scalar(f"plots/terrain/{name}", t, w, name)
        if msg.solver_ok != self._solver_ok:
            if self._solver_ok is not None or not msg.solver_ok:
                text = "terrain: weight solve failed, weights kept" if not msg.solver_ok else "terrain: solving again"
                self.event(t, text, "WARN" if not msg.solver_ok else "INFO")
            self._solver_ok = msg.solver_ok
        # "none of these grounds" on the same plot (a probability, like the weights), and an event each time the
        # terrain service's hysteretic decision changes (not each time the probability crosses 0.5)
        self._scalar("plots/terrain/unknown", t, msg.unknown, "unknown")
        if msg.unknown_active != self._unknown:
            if self._unknown is not None or msg.unknown_active:
                nearest = msg.names[max(range(len(msg.weights)), key=msg.weights.__getitem__)]
                how = _CHANNEL_SAYS.get(msg.unknown_channel, "")
                text = (f"terrain: ground unknown, none of the trained grounds explains it{how} (P(unknown) "
                        f"{msg.unknown:.2f}, nearest {nearest})" if msg.unknown_active else
                        f"terrain: ground known again ({nearest}, P(unknown) {msg.unknown:.2f})")
                self.event(t, text, "WARN" if msg.unknown_active else "INFO")
            self._unknown = msg.unknown_active

    def _task(self, msg: Task, t: int) -> None:
        import rerun as rr

        if self.task is not None and self.task.model_dump(exclude={"header"}) == msg.model_dump(exclude={"header"}):
            return
        first = self.task is None
        self.task = msg
        try:
            self.outline = task_from_message(msg).outline()
        except ValueError as exc:  # the message validated, but the core's task refuses it: say so, draw nothing
            self.outline = None
            self.event(t, f"task not drawn: {exc}", "WARN")
            return
        # the task is static (the map); a later, different task replaces it
        for entity, (layer, lines) in geo.task_lines(self.outline).items():
            style = geo.LAYERS[layer]
            self.rec.log(f"map/{entity}", rr.LineStrips2D(lines, colors=[style.color], radii=style.radius,
                                                         draw_order=style.order), static=True)
        circles = self.outline.circles
        if circles.shape[0]:
            style = geo.LAYERS["obstacles"]
            self.rec.log("map/obstacles", rr.Points2D(circles[:, :2], radii=circles[:, 2], colors=[style.color],
                                                      draw_order=style.order), static=True)
        text = "task: " + self.outline.summary
        self.event(t, text if first else "task changed: " + text)

    def _costmap(self, msg: OccupancyGrid, t: int) -> None:
        """A grid's lethal cells, as the map (static, like the task's obstacles); drawn again only when it changes."""
        import rerun as rr

        key = msg.model_dump_json(exclude={"header": {"stamp_ns", "seq"}})
        if key == self._grid_key:
            return
        first = self._grid_key is None
        self._grid_key = key
        centres, radius = geo.lethal_cells(msg)
        style = geo.LAYERS["costmap"]
        self.rec.log("map/costmap", rr.Points2D(centres, radii=radius, colors=[style.color], draw_order=style.order),
                     static=True)
        text = f"costmap: {msg.width} x {msg.height} cells of {msg.resolution:g} m, {len(centres)} lethal"
        self.event(t, text if first else "costmap changed: " + text)

    def _plan(self, msg: Plan, t: int) -> None:
        import rerun as rr

        if msg.header.seq < self._plan_seq:  # a new planner process counts from 0 again
            self.event(t, "planner restarted (plan sequence began again)", "WARN")
            self._plans = 0
        self._plan_seq = msg.header.seq
        self._plans += 1
        if msg.weights_stale != self._stale:
            if self._stale is not None or msg.weights_stale:
                text = "planner: terrain weights stale" if msg.weights_stale else "planner: terrain weights fresh again"
                self.event(t, text, "WARN" if msg.weights_stale else "INFO")
            self._stale = msg.weights_stale
        self._at(t)
        states = geo.plan_states(msg)
        if states is not None:
            self._static("map/plan/nominal", _line("nominal"))
            self.rec.log("map/plan/nominal", rr.LineStrips2D.from_fields(strips=_strips([states[:, :2]])))
            ellipses = geo.plan_ellipses(msg, states, self.opt.ellipse_every)
            if ellipses is not None:
                self._static("map/plan/covariance", _line("covariance"))
                self.rec.log("map/plan/covariance", rr.LineStrips2D.from_fields(strips=_strips(ellipses)))
            if msg.tightened:
                self._tightened(msg, states, t)
        if (self._plans - 1) % self.opt.samples_every == 0 and (
            drawn := geo.rollouts(msg, self.opt.max_samples, self.opt.sample_stride)
        ) is not None:
            self._static("map/plan/rollouts", _line("samples"))
            # every `sample_stride`-th point of each rollout (and its last): smooth curves, a fraction of the bytes
            points, colors = drawn
            self.rec.log("map/plan/rollouts", rr.LineStrips2D.from_fields(strips=points, colors=geo.pack_rgba(colors)))
        if (summary := geo.rollout_cost_summary(msg)) is not None:
            self._scalar("plots/cost/min", t, summary[0])
            self._scalar("plots/cost/median", t, summary[1])
        for name, value in msg.critic_costs.items():
            self._scalar(f"plots/critics/{name}", t, value, name)
        if msg.effective_samples is not None:
            self._scalar("plots/samples/effective", t, msg.effective_samples, "effective samples")
        self._timings(msg, t)

    def _tightened(self, msg: Plan, states: np.ndarray, t: int) -> None:
        import rerun as rr

        ends = geo.tightening(msg)
        assert ends is not None  # called with a tightening only
        outline = self.outline
        if outline is not None and outline.bounds == "half_width":
            self._scalar("plots/tightening/nominal", t, outline.half_width)
        self._scalar("plots/tightening/first", t, ends[0])
        self._scalar("plots/tightening/last", t, ends[1])
        if outline is None:
            return
        # the bounds as the task's kind says what they are: per step of the horizon a lane's tightened half-width on
        # either side of the centre, where the plan is; or the circles grown by the inflation
        layer, lines = geo.plan_bounds(msg, states, outline)
        if lines:
            entity = _BOUND_ENTITIES[layer]
            self._static(entity, _line(layer))
            self.rec.log(entity, rr.LineStrips2D.from_fields(strips=_strips(lines)))

    def _timings(self, msg: Plan, t: int) -> None:
        if self._plans <= self.opt.timing_warmup_plans:
            self._warmup_ms.append(msg.timings_ms.get("total", max(msg.timings_ms.values(), default=0.0)))
            if self._plans == self.opt.timing_warmup_plans:
                worst = max(self._warmup_ms)
                self.event(t, f"planner start-up: first {self._plans} plans took up to {worst:.0f} ms (not plotted)")
                self._warmup_ms = []
            return
        for name, ms in msg.timings_ms.items():
            self._scalar(f"plots/planner/{name}", t, ms, name)

    def _heartbeat(self, hb: Heartbeat, t: int) -> None:
        prev = self._health.get(hb.service)
        self._health[hb.service] = hb
        name = hb.service
        if prev is None:
            self.event(t, f"{name}: up ({hb.status})", "INFO" if hb.status == "ok" else "WARN")
            return
        if hb.header.seq < prev.header.seq or hb.published < prev.published or hb.received < prev.received:
            self.event(t, f"{name}: restarted", "WARN")
            return
        if hb.status != prev.status:
            level = {"ok": "INFO", "degraded": "WARN", "failing": "ERROR"}[hb.status]
            self.event(t, f"{name}: status {prev.status} -> {hb.status}", level)
        if hb.rejected > prev.rejected:
            self.event(
                t,
                f"{name}: rejected {hb.rejected - prev.rejected} input(s) (total {hb.rejected}): {hb.last_error}",
                "WARN",
            )
        elif hb.last_error and hb.last_error != prev.last_error:
            self.event(t, f"{name}: {hb.last_error}", "WARN")
        changed = {
            k: v - prev.counts.get(k, 0)
            for k, v in hb.counts.items()
            if v != prev.counts.get(k, 0) and k not in ROUTINE_HEALTH
        }
        if changed:
            self.event(
                t, f"{name}: " + ", ".join(f"{k} {d:+d} (now {hb.counts[k]})" for k, d in sorted(changed.items()))
            )
        flipped = {k: v for k, v in hb.flags.items() if v != prev.flags.get(k, False) and k not in ROUTINE_HEALTH}
        if flipped:
            self.event(
                t, f"{name}: " + ", ".join(f"{k} {'on' if v else 'off'}" for k, v in sorted(flipped.items())), "WARN"
            )
