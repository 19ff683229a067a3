"""`gpmppi dataset`: drive the physics plant with excitation commands over terrains and record MCAP.

Per tick k (dt = 0.1 s) the file holds, with the same stamp t_k: the measured `State` on
`gpmppi/{robot}/state`, the `Command` applied over [t_k, t_k + dt) on `gpmppi/{robot}/cmd`, and the
`TerrainLabel` on `gpmppi/{robot}/terrain/label`. Terrains follow one another on one timeline with a
one-second gap between them. The file is written under a temporary name and renamed when complete,
so an interrupted run leaves nothing half-written. `read_dataset` turns such a file (or a real robot
log with state + cmd and no labels) back into per-terrain arrays (`tools.log_reader`, the one log reader).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from gpmppi.plant.excitation import TerrainRun, simulate_dataset
from gpmppi.plant.residual_stats import pattern_separation, residual_stats, theta_from_runs
from gpmppi.plant.terrains import TerrainFileError, load_terrains
from schemas.keys import DEFAULT_ROBOT, key_for
from schemas.messages import Command, Header, State, TerrainLabel
from services.recording.mcap_writer import McapWriter
from tools.cli_checks import OUT_FILE, fail
from tools.log_reader import NS, read_log_runs, runs_by_ground

DATASET_DT = 0.1
TERRAIN_GAP_S = 1.0
DEFAULT_TERRAINS = ("tile", "asphalt", "grass")


def write_dataset(path: Path, runs: dict[str, TerrainRun], robot: str = DEFAULT_ROBOT) -> int:
    """Write runs to MCAP at `path` atomically (temporary file + rename); returns the number of ticks."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.partial-{os.getpid()}{path.suffix}")
    keys = {name: key_for(name, robot) for name in ("state", "cmd", "terrain_label")}
    ticks = 0
    offset_s = 0.0
    try:
        with McapWriter(tmp) as writer:
            for terrain, run in runs.items():
                for k in range(len(run.command)):
                    stamp = int(round((offset_s + run.time[k]) * NS))
                    header = Header(stamp_ns=stamp, frame_id="odom", seq=ticks)
                    s, c = run.state[k], run.command[k]
                    writer.write(keys["state"], State(header=header, x=s[0], y=s[1], theta=s[2], v=s[3], omega=s[4]),
                                 log_time_ns=stamp)
                    writer.write(keys["cmd"], Command(header=header, v_ref=c[0], omega_ref=c[1]), log_time_ns=stamp)
                    writer.write(keys["terrain_label"], TerrainLabel(header=header, terrain=terrain),
                                 log_time_ns=stamp)
                    ticks += 1
                offset_s += len(run.command) * run.dt + TERRAIN_GAP_S
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return ticks


def read_dataset(
    path: str | Path, robot: str = DEFAULT_ROBOT, terrain: str | None = None, dt: float = DATASET_DT
) -> dict[str, list[TerrainRun]]:
    """Per-terrain contiguous runs of dt ticks from a recording: a `gpmppi dataset` file or a stack recording
    (`gpmppi calibrate drive`, `gpmppi launch --record`, a robot log with state + cmd). The runs of
    `tools.log_reader.read_log_runs` (its docstring holds the pairing rule and the labels) by ground; its errors are
    `DataError`s (a `ValueError`)."""
    return runs_by_ground(read_log_runs(path, dt, terrain, robot))


def register(app: typer.Typer) -> None:
    """Add `gpmppi dataset`."""

    @app.command("dataset")
    def dataset(
        output: Path = typer.Option(
            ..., "-o", "--output", metavar=OUT_FILE, help="MCAP file to write (written atomically)"
        ),
        terrain: list[str] = typer.Option(
            list(DEFAULT_TERRAINS), "--terrain", "-t", help="terrain to drive on (repeat for several)"
        ),
        terrain_file: Path | None = typer.Option(None, "--terrain-file", help="terrain set YAML (default: shipped)"),
        distance: float = typer.Option(2000.0, "--distance", min=1.0, help="metres driven per terrain"),
        seed: int = typer.Option(0, "--seed", min=0, help="seed of the excitation and the sensor noise"),
        robot: str = typer.Option(DEFAULT_ROBOT, "--robot", help="robot name in the key expressions"),
        lane_holds: float = typer.Option(
            0.0, "--lane-holds", min=0.0, max=0.9,
            help="share of the segments that are long holds (5-8 s) where the planner drives (v_ref 0.8-1.8 m/s, "
                 "|omega_ref| <= 0.8 rad/s), for the terrain calibration's steady map; 0: the plain excitation"),
        top_holds: float = typer.Option(
            0.0, "--top-holds", min=0.0, max=1.0,
            help="chance of a straight hold near the robot's top speed (0.7-1.0 x max_speed, 5-8 s) added after each "
                 "segment, its metres on top of --distance (the plain segments stay as they are); 0: none"),
        force: bool = typer.Option(False, "--force", help="replace an existing --output file"),
    ) -> None:
        """Drive the physics plant with random excitation over terrains; record state, cmd and labels."""
        console = Console()
        try:
            terrains = load_terrains(terrain_file)
            for name in terrain:
                terrains.get(name)
        except (TerrainFileError, KeyError) as exc:
            fail(str(exc.args[0]))
        started = time.perf_counter()
        with Progress(
            TextColumn("[bold]{task.description:>10}"), BarColumn(), MofNCompleteColumn(),
            TextColumn("m"), TimeElapsedColumn(), console=console,
        ) as progress:
            tasks = {name: progress.add_task(name, total=int(distance)) for name in terrain}
            runs = simulate_dataset(
                terrains, list(terrain), distance=distance, seed=seed, dt=DATASET_DT, lane_holds=lane_holds,
                top_holds=top_holds, progress=lambda name, d: progress.update(tasks[name], completed=int(d)),
            )
        simulated = time.perf_counter() - started
        ticks = write_dataset(output, runs, robot)
        sim_seconds = ticks * DATASET_DT
        table = Table(title=f"{output}: {ticks} ticks; simulated {sim_seconds:.0f} s of driving in {simulated:.1f} s "
                            f"({sim_seconds / simulated:.0f}x real time), total {time.perf_counter() - started:.1f} s")
        for col in ("terrain", "ticks", "metres", "seconds", "mean v", "mean |w|"):
            table.add_column(col, justify="right")
        for name, run in runs.items():
            table.add_row(name, str(len(run.command)), f"{run.distance:.0f}", f"{len(run.command) * run.dt:.0f}",
                          f"{run.true_state[:, 3].mean():.2f}", f"{np.abs(run.true_state[:, 4]).mean():.2f}")
        console.print(table)

    @app.command("dataset-stats")
    def dataset_stats(
        path: Path = typer.Argument(..., help="dataset MCAP (from `gpmppi dataset` or a robot log)"),
        fit_on: list[str] = typer.Option(
            [], "--fit-on", help="terrains whose data identify theta (repeat; default: all in the file)"
        ),
        terrain: str | None = typer.Option(None, "--terrain", "-t", help="terrain name of an unlabelled log"),
        robot: str = typer.Option(DEFAULT_ROBOT, "--robot", help="robot name in the key expressions"),
    ) -> None:
        """Identify theta and print the nominal model's one-step residual statistics per terrain."""
        console = Console()
        try:
            runs = read_dataset(path, robot=robot, terrain=terrain)
        except (ValueError, FileNotFoundError) as exc:
            fail(str(exc))
        unknown = sorted(set(fit_on) - set(runs))
        if unknown:
            fail(f"--fit-on {unknown} not in {path} (it has {sorted(runs)})")
        fit_runs = [r for name in (fit_on or list(runs)) for r in runs[name]]
        theta = theta_from_runs(fit_runs)
        console.print(f"theta (fit on {fit_on or sorted(runs)}): {np.array2string(theta, precision=4)}")
        stats = {name: residual_stats(theta, name, rs) for name, rs in runs.items()}
        table = Table(title="one-step residuals of the nominal model over dt [m/s, rad/s] (w = omega; box = moderate "
                            "driving: v_ref<=1.7, |w_ref|<=1.5, v<=1.5, |w|<=1.5)")
        for col in ("terrain", "n", "RMS v", "RMS w", "mean v", "mean w", "box n", "box RMS v", "box RMS w"):
            table.add_column(col, justify="right")
        for name, st in stats.items():
            table.add_row(name, str(st.n), f"{st.rms[0]:.4f}", f"{st.rms[1]:.4f}", f"{st.mean[0]:+.4f}",
                          f"{st.mean[1]:+.4f}", str(st.n_moderate), f"{st.rms_moderate[0]:.4f}",
                          f"{st.rms_moderate[1]:.4f}")
        console.print(table)
        names = list(stats)
        if len(names) > 1:
            sep = Table(title="pattern separation: RMS z-score of binned mean residuals (about 1 = same pattern)")
            for col in ("pair", "v", "omega"):
                sep.add_column(col, justify="right")
            for i, a in enumerate(names):
                for b in names[i + 1 :]:
                    z = pattern_separation(stats[a], stats[b])
                    sep.add_row(f"{a} - {b}", f"{z[0]:.1f}", f"{z[1]:.1f}")
            console.print(sep)
