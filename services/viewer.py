"""viewer: streams states, plans, the task and health to rerun (spawned viewer, an .rrd file, or a gRPC URL).

`RerunMapper` holds the message -> rerun mapping so replay tools can feed it messages read from MCAP.
Map view: lane and its tightened bounds, obstacles and their inflation, sampled rollouts, nominal plan,
covariance ellipses, the driven path. Time series: speeds, commands, planner timings, terrain weights.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Literal

import numpy as np
import zenoh
from pydantic import Field

from schemas import (
    BaseCommand,
    Command,
    DecodeError,
    Heartbeat,
    Message,
    Plan,
    State,
    Task,
    TerrainWeights,
    decode,
    model_for_key,
)
from services.node import Node, NodeSettings

if TYPE_CHECKING:
    import rerun as rr
    import rerun.blueprint as rrb

TIMELINE = "stamp"


class Settings(NodeSettings):
    service: str = Field("viewer", description="service name")
    mode: Literal["spawn", "save", "connect", "off"] = Field("save", description="where the rerun stream goes")
    path: str = Field("runs/view.rrd", description="output file for mode 'save'")
    url: str = Field("rerun+http://127.0.0.1:9876/proxy", description="viewer gRPC URL for mode 'connect'")
    key_expr: str = Field("gpmppi/**", description="what to show")
    path_length: int = Field(2000, gt=1, description="points of the driven path kept on screen")
    ellipse_every: int = Field(5, ge=1, description="draw every n-th covariance ellipse of the plan")


def _ellipse(cx: float, cy: float, sxx: float, sxy: float, syy: float, n_sigma: float = 2.0, n: int = 24) -> np.ndarray:
    cov = np.array([[sxx, sxy], [sxy, syy]])
    vals, vecs = np.linalg.eigh(cov)
    vals = np.clip(vals, 0.0, None)
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    circle = np.stack([np.cos(a), np.sin(a)], axis=1)
    return np.array([cx, cy]) + n_sigma * (circle * np.sqrt(vals)) @ vecs.T


def _circle(x: float, y: float, r: float, n: int = 48) -> np.ndarray:
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    return np.stack([x + r * np.cos(a), y + r * np.sin(a)], axis=1)


def _offset(polyline: np.ndarray, distance: np.ndarray | float, closed: bool) -> np.ndarray:
    """The polyline shifted left by `distance` (per vertex or constant) along its normals."""
    p = np.asarray(polyline, dtype=np.float64)
    nxt = np.roll(p, -1, axis=0) if closed else np.vstack([p[1:], 2 * p[-1] - p[-2]])
    prv = np.roll(p, 1, axis=0) if closed else np.vstack([2 * p[0] - p[1], p[:-1]])
    t = nxt - prv
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    normal = np.stack([-t[:, 1], t[:, 0]], axis=1)
    out = p + normal * np.reshape(distance, (-1, 1))
    return np.vstack([out, out[:1]]) if closed else out


class RerunMapper:
    """Logs gpmppi messages to a rerun recording stream."""

    def __init__(self, rec: rr.RecordingStream, path_length: int = 2000, ellipse_every: int = 5) -> None:
        self.rec = rec
        self.path: list[list[float]] = []
        self.path_length = path_length
        self.ellipse_every = ellipse_every
        self.task: Task | None = None

    @staticmethod
    def blueprint() -> rrb.Blueprint:
        import rerun.blueprint as rrb

        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Spatial2DView(origin="map", name="map"),
                rrb.Vertical(
                    rrb.TimeSeriesView(origin="plots/velocity", name="velocity"),
                    rrb.TimeSeriesView(origin="plots/planner", name="planner [ms]"),
                    rrb.TimeSeriesView(origin="plots/terrain", name="terrain weights"),
                ),
                column_shares=[3, 2],
            )
        )

    def log(self, key: str, msg: Message) -> None:
        import rerun as rr

        stamp = msg.header.stamp_ns or time.time_ns()
        rr.set_time(TIMELINE, timestamp=np.datetime64(stamp, "ns"), recording=self.rec)
        if isinstance(msg, State):
            if key.endswith("/odom/raw"):
                return
            self.path.append([msg.x, msg.y])
            del self.path[: -self.path_length]
            self.rec.log("map/robot", rr.Points2D([[msg.x, msg.y]], radii=0.25, colors=[[30, 120, 255]]))
            heading = [[msg.x, msg.y], [msg.x + 0.6 * np.cos(msg.theta), msg.y + 0.6 * np.sin(msg.theta)]]
            self.rec.log("map/robot_heading", rr.LineStrips2D([heading], colors=[[30, 120, 255]]))
            self.rec.log("map/driven_path", rr.LineStrips2D([self.path], colors=[[30, 120, 255]], radii=0.03))
            self.rec.log("plots/velocity/v", rr.Scalars(msg.v))
            self.rec.log("plots/velocity/omega", rr.Scalars(msg.omega))
        elif isinstance(msg, Plan):
            self._log_plan(msg)
        elif isinstance(msg, Task):
            self._log_task(msg)
        elif isinstance(msg, Command):
            self.rec.log("plots/velocity/v_ref", rr.Scalars(msg.v_ref))
            self.rec.log("plots/velocity/omega_ref", rr.Scalars(msg.omega_ref))
        elif isinstance(msg, BaseCommand):
            self.rec.log("plots/velocity/v_base", rr.Scalars(msg.v))
        elif isinstance(msg, TerrainWeights):
            for name, w in zip(msg.names, msg.weights, strict=True):
                self.rec.log(f"plots/terrain/{name}", rr.Scalars(w))
        elif isinstance(msg, Heartbeat):
            self.rec.log(
                f"health/{msg.service}",
                rr.TextLog(
                    f"rate {msg.rate_hz:.1f} Hz rx {msg.received} rej {msg.rejected} tx {msg.published} "
                    f"{msg.last_error}"
                ),
            )

    def _log_task(self, msg: Task) -> None:
        import rerun as rr

        if self.task is not None and self.task.model_dump(exclude={"header"}) == msg.model_dump(exclude={"header"}):
            return
        self.task = msg
        if msg.kind == "lane":
            c = np.asarray(msg.centerline)
            centre = np.vstack([c, c[:1]]) if msg.closed else c
            edges = [_offset(c, msg.half_width, msg.closed), _offset(c, -msg.half_width, msg.closed)]
            self.rec.log("map/lane/centre", rr.LineStrips2D([centre], colors=[[150, 150, 150]]), static=True)
            self.rec.log("map/lane/edges", rr.LineStrips2D(edges, colors=[[60, 60, 60]], radii=0.05), static=True)
        else:
            circles = [_circle(o.x, o.y, o.r) for o in msg.obstacles]
            self.rec.log("map/obstacles", rr.LineStrips2D(circles, colors=[[200, 60, 60]], radii=0.05), static=True)
            if msg.goal is not None:
                self.rec.log(
                    "map/goal",
                    rr.LineStrips2D([_circle(*msg.goal, msg.goal_tolerance)], colors=[[40, 180, 40]]),
                    static=True,
                )

    def _log_plan(self, msg: Plan) -> None:
        import rerun as rr

        states = np.asarray(msg.states)
        if states.size:
            self.rec.log("map/plan/nominal", rr.LineStrips2D([states[:, :2]], colors=[[255, 160, 0]], radii=0.04))
        if msg.samples:
            self.rec.log("map/plan/samples", rr.LineStrips2D(msg.samples, colors=[[255, 220, 150]], radii=0.01))
        if msg.cov_xy and states.size:
            ellipses = [
                _ellipse(states[k, 0], states[k, 1], *msg.cov_xy[k])
                for k in range(0, min(len(msg.cov_xy), len(states)), self.ellipse_every)
            ]
            self.rec.log("map/plan/covariance", rr.LineStrips2D(ellipses, colors=[[200, 100, 255]], radii=0.01))
        if msg.tightened and self.task is not None and states.size:
            if self.task.kind == "lane":
                self._log_tightened_lane(msg.tightened)
            else:
                inflation = float(msg.tightened[0])
                circles = [_circle(o.x, o.y, o.r + inflation) for o in self.task.obstacles]
                self.rec.log("map/obstacles_inflated", rr.LineStrips2D(circles, colors=[[255, 120, 120]], radii=0.02))
        for name, ms in msg.timings_ms.items():
            self.rec.log(f"plots/planner/{name}", rr.Scalars(ms))

    def _log_tightened_lane(self, tightened: list[float]) -> None:
        import rerun as rr

        assert self.task is not None
        c = np.asarray(self.task.centerline)
        # the current tightened half-width, drawn along the whole lane
        r = float(tightened[0])
        edges = [_offset(c, r, self.task.closed), _offset(c, -r, self.task.closed)]
        self.rec.log("map/lane/tightened", rr.LineStrips2D(edges, colors=[[255, 200, 0]], radii=0.02))


def open_stream(settings: Settings) -> rr.RecordingStream | None:
    import rerun as rr

    if settings.mode == "off":
        return None
    rec = rr.RecordingStream("gpmppi")
    if settings.mode == "spawn":
        rec.spawn()
    elif settings.mode == "connect":
        rec.connect_grpc(settings.url)
    else:
        from pathlib import Path

        Path(settings.path).parent.mkdir(parents=True, exist_ok=True)
        rec.save(settings.path)
    rec.send_blueprint(RerunMapper.blueprint())
    return rec


def run(settings: Settings) -> int:
    rec = open_stream(settings)
    mapper = RerunMapper(rec, settings.path_length, settings.ellipse_every) if rec is not None else None
    try:
        with Node(settings) as node:
            assert node.session is not None
            sub = node.session.declare_subscriber(settings.key_expr, zenoh.handlers.FifoChannel(10_000))
            while node.ok():
                handled = 0
                while (sample := sub.try_recv()) is not None:
                    key = str(sample.key_expr)
                    try:
                        msg = decode(model_for_key(key), sample.payload.to_bytes(), settings.max_payload_bytes)
                    except (KeyError, DecodeError) as exc:
                        node.reject(f"{key}: {exc}")
                        continue
                    node.counters.received += 1
                    if mapper is not None:
                        mapper.log(key, msg)
                    handled += 1
                if handled:
                    node.cycle()
                node.spin_once(0.01)
    finally:
        if rec is not None:
            rec.flush()
            rec.disconnect()
    return 0
