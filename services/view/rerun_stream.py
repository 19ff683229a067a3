"""The rerun stream and its layout (blueprint), shared by the viewer service and the offline converter."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from services.view.rerun_map import EVENTS

if TYPE_CHECKING:
    import rerun as rr
    import rerun.blueprint as rrb


def blueprint() -> rrb.Blueprint:
    """The layout: the map beside a grid of time series, the event log below."""
    import rerun.blueprint as rrb

    def plot(origin: str, name: str) -> rrb.TimeSeriesView:
        return rrb.TimeSeriesView(
            origin=origin,
            name=name,
            plot_legend=rrb.PlotLegend(corner="LeftTop"),
            axis_x=rrb.TimeAxis(link="LinkToGlobal"),  # the plots share one time range
        )

    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Spatial2DView(origin="map", name="map"),
                rrb.Grid(
                    plot("plots/v", "v [m/s]"),
                    plot("plots/omega", "omega [rad/s]"),
                    plot("plots/terrain", "terrain weights"),
                    plot("plots/planner", "planner [ms] (start-up excluded)"),
                    plot("plots/tightening", "lane half-width / inflation [m]"),
                    plot("plots/cost", "rollout cost"),
                    plot("plots/critics", "critic costs of the plan"),
                    plot("plots/samples", "effective samples of the update"),
                    grid_columns=2,
                ),
                column_shares=[1, 1],
            ),
            rrb.TextLogView(origin=EVENTS, name="events"),
            row_shares=[4, 1],
        ),
        collapse_panels=True,
    )


def open_stream(
    mode: str, target: str | None = None, serve_port: int = 9876, batch_s: float = 0.25
) -> rr.RecordingStream:
    """A recording stream to `mode`: 'save' (target: .rrd path), 'spawn', 'connect' (target: URL) or 'serve'
    (a gRPC server on `serve_port`), with the blueprint sent; rows are batched into chunks for `batch_s` [s]."""
    from datetime import timedelta

    import rerun as rr

    # rows logged within `batch_s` travel as one chunk: per-message chunks would each carry their own schema
    rec = rr.RecordingStream("gpmppi", batcher_config=rr.ChunkBatcherConfig(flush_tick=timedelta(seconds=batch_s)))
    # one timeline, `stamp`: the SDK's own log_time / log_tick would add two columns to every row
    rec.set_log_time_enabled(False)
    rec.set_log_tick_enabled(False)
    if mode == "spawn":
        rec.spawn()
    elif mode == "connect":
        rec.connect_grpc(target) if target else rec.connect_grpc()
    elif mode == "serve":
        url = rec.serve_grpc(grpc_port=serve_port)
        print(f"rerun: serving on {url} (open it with `rerun {url}`)", flush=True)
    elif mode == "save":
        if not target:
            raise ValueError("rerun mode 'save' needs an output .rrd path")
        Path(target).parent.mkdir(parents=True, exist_ok=True)
        rec.save(target)
    else:
        raise ValueError(f"rerun mode {mode!r} is not one of save, spawn, connect, serve")
    rec.send_blueprint(blueprint())
    return rec
