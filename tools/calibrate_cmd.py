"""`gpmppi calibrate drive`: the calibration drive through the running stack, recorded for `gpmppi train`.

The stack is the launch file's (default: the shipped simulated Jackal) with its planner replaced by the `calibrate`
service and its terrain service left out: ingress, egress (its limits, watchdog and e-stop apply to the drive as to
the planner), the sim plant on the ground named (when the file runs one) and the recorder, recording to one MCAP per
run, `DIR/calib-GROUND-TIME.mcap`. The drive ends at its distance or time; Ctrl-C engages the e-stop (egress holds
zero, the recorder records it), then stops the stack and closes the recording. `--resume` drives only what the
recordings of that ground in DIR do not already hold.
"""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any

import typer

from tools.cli_checks import OUT_DIR, fail

GROUND_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")  # it names files and keys
PROGRESS_EVERY_S = 10.0
# gpmppi.plant.area_excitation.MIN_AREA_M, not imported: the command tree is built without numba (tests check they
# agree)
MIN_AREA_M = 6.0
ESTOP_HOLD_S = 0.6  # after Ctrl-C: egress's zero reaches the base and the recorder before the stack stops


def calibration_runs(folder: Path, ground: str) -> list[Path]:
    """The recordings of `ground` in `folder`, oldest first (by name: the time is in it)."""
    return sorted(folder.glob(f"calib-{ground}-*.mcap"))


def driven(folder: Path, ground: str, robot: str) -> tuple[float, float, int]:
    """(metres, seconds, recordings) of `ground` the recordings in `folder` hold (state ticks paired with commands,
    as `read_dataset` reads them)."""
    from tools.dataset import read_dataset

    metres = seconds = 0.0
    files = calibration_runs(folder, ground)
    for path in files:
        try:
            runs = read_dataset(path, robot=robot).get(ground, [])
        except ValueError:  # a run stopped before its first command: nothing driven
            continue
        metres += sum(r.distance for r in runs)
        seconds += sum(len(r.command) * r.dt for r in runs)
    return metres, seconds, len(files)


def stack_edit(ground: str, drive: dict[str, Any]) -> Any:
    """The launch file's change: its (first) planner becomes the calibration service, other planners and the
    terrain service are off, the sim drives on `ground`."""
    from services.launch.launch_file import LaunchFile, ServiceEntry

    def edit(launch: LaunchFile) -> LaunchFile:
        services: list[ServiceEntry] = []
        placed = False
        for e in launch.services:
            kind = e.kind or e.name
            if kind == "planner" and not placed:
                # in the planner's place (the same index: a problem found later points at its line)
                e = ServiceEntry(name="calibrate", kind="calibrate", required=True, config=drive)
                placed = True
            elif kind in ("planner", "terrain"):
                e = e.model_copy(update={"enabled": False})
            elif kind == "sim":
                e = e.model_copy(update={"config": {**e.config, "terrain": ground}})
            services.append(e)
        if not placed:
            services.append(ServiceEntry(name="calibrate", kind="calibrate", required=True, config=drive))
        spares = None if launch.spares is None else [s for s in launch.spares if s != "planner"]
        return launch.model_copy(update={"services": services, "spares": spares})

    return edit


def check_ground(launch_path: Path, ground: str) -> str:
    """The launch file's robot; `fail` if a sim service in it does not know `ground`."""
    from gpmppi.plant.terrains import load_terrains
    from services.launch.launch_file import load_launch

    launch, _ = load_launch(launch_path)
    for e in launch.services:
        if (e.kind or e.name) == "sim" and e.enabled:
            terrains = load_terrains(e.config.get("terrain_file"))
            if ground not in terrains.names:
                fail(f"--ground {ground!r}: the sim plant of {launch_path} has no such ground; known: "
                     f"{', '.join(terrains.names)} (or add it to its terrain_file)")
    return launch.robot


def register(app: typer.Typer) -> None:
    """Add `gpmppi calibrate drive`."""
    calibrate_app = typer.Typer(help="Calibration drives: the logs a robot's model is fitted from.",
                                no_args_is_help=True)

    @calibrate_app.command("drive")
    def drive(
        terrain: str = typer.Option(
            ..., "--ground", "--terrain", "-t", help="name of the ground driven on (recorded as its terrain label)"
        ),
        area: float = typer.Option(
            20.0, "--area", min=MIN_AREA_M, max=10_000.0,
            help="side of the free square, centred on the robot's start pose, the drive stays inside [m]",
        ),
        distance: float | None = typer.Option(None, "--distance", min=1.0, max=1e6, help="metres to drive"),
        minutes: float | None = typer.Option(None, "--minutes", min=0.05, max=24 * 60.0, help="minutes to drive"),
        record: Path = typer.Option(
            ..., "--record", metavar=OUT_DIR, help="folder for the recordings (made if missing; one MCAP per run, "
            "calib-GROUND-TIME.mcap)",
        ),
        launch_file: Path | None = typer.Option(
            None, "--launch-file", help="launch YAML whose ingress, egress and sim run the drive (default: the "
            "simulated Jackal)",
        ),
        resume: bool = typer.Option(False, "--resume", help="drive only what the recordings of GROUND in the "
                                    "--record folder do not already hold"),
        speed: float = typer.Option(1.5, "--speed", min=0.1, max=2.0, help="speed cap of the commands [m/s]"),
        seed: int | None = typer.Option(
            None, "--seed", min=0, help="seed of the command stream (default: the number of earlier recordings "
            "of GROUND in the folder, so a resumed drive does not repeat the first)",
        ),
        lane_holds: float = typer.Option(
            0.0, "--lane-holds", min=0.0, max=0.9,
            help="share of the segments that are long holds (5-8 s) where the planner drives (v_ref 0.8-1.8 m/s, "
                 "|omega_ref| <= 0.8 rad/s), kept inside the area: a log for `gpmppi train --calibration-log`; 0: the "
                 "plain drive"),
        port: int | None = typer.Option(None, "--port", min=1, max=65535, help="router port on 127.0.0.1"),
    ) -> None:
        """Drive the robot with excitation commands inside a free area on one ground and record it (the logs
        `gpmppi train` fits a robot from)."""
        from services.launch.launch_file import DEFAULT_LAUNCH

        ground = terrain
        if (distance is None) == (minutes is None):
            fail("give one target: --distance METRES or --minutes MINUTES")
        if not GROUND_NAME.match(ground):
            fail(f"--ground {ground!r}: use letters, digits, '_', '-' or '.' (it names the recordings)")
        path = launch_file or DEFAULT_LAUNCH
        robot = check_ground(path, ground)
        done_m = done_s = 0.0
        earlier = 0
        if record.is_dir():
            done_m, done_s, earlier = driven(record, ground, robot) if resume else (0.0, 0.0, 0)
            earlier = len(calibration_runs(record, ground))
        want_m = None if distance is None else distance - done_m
        want_s = None if minutes is None else minutes * 60.0 - done_s
        if resume:
            typer.echo(f"resume: {earlier} recording(s) of {ground} in {record} hold {done_m:.0f} m, "
                       f"{done_s / 60:.1f} min")
            if (want_m is not None and want_m <= 0.5) or (want_s is not None and want_s <= 1.0):
                typer.echo("nothing left to drive")
                raise typer.Exit(0)
        config: dict[str, Any] = {"ground": ground, "area_m": area, "v_max": speed,
                                  "seed": earlier if seed is None else seed, "lane_holds": lane_holds}
        config.update({"distance_m": want_m} if want_m is not None else {"duration_s": want_s})
        record.mkdir(exist_ok=True)
        out = record / f"calib-{ground}-{time.strftime('%Y%m%d-%H%M%S')}.mcap"
        code, summary = run_drive(path, out, stack_edit(ground, config), port)
        metres, seconds, _ = driven(record, ground, robot) if Path(summary.recording or out).is_file() else (0, 0, 0)
        typer.echo(f"recording: {summary.recording}; {ground} in {record}: {metres:.0f} m, {seconds / 60:.1f} min "
                   "in all")
        raise typer.Exit(code)

    app.add_typer(calibrate_app, name="calibrate")


def run_drive(path: Path, out: Path, edit: Any, port: int | None) -> tuple[int, Any]:
    """Run the edited launch until the calibration service is done or Ctrl-C; (exit code, summary)."""
    from services.launch.launcher import RouterUnreachable, run_launch

    try:
        return run_launch(path, record=str(out), port=port, then=calibration_drive, edit=edit)
    except (FileNotFoundError, ValueError, TimeoutError, RouterUnreachable) as exc:
        fail(str(exc))
        raise AssertionError from exc  # fail() raises


def calibration_drive(launcher: Any, monitor: Any) -> None:
    """While the stack runs: report progress; return when the calibration service is done, or, on Ctrl-C, after
    engaging the e-stop, so egress holds the robot at zero before the stack stops."""
    from schemas import EStop, encode
    from schemas.keys import key_for

    next_report = time.monotonic() + PROGRESS_EVERY_S
    while not launcher.stop_event.wait(0.25):
        with monitor.lock:
            hb = monitor.heartbeats.get("calibrate")
        if hb is None:
            continue
        if hb.flags.get("done"):
            lanes = hb.counts.get("lane_holds", 0)
            launcher.say("calibrate", f"done: {hb.counts.get('distance_dm', 0) / 10:.0f} m in "
                                      f"{hb.counts.get('driven_ds', 0) / 10:.0f} s"
                                      + (f", {lanes} lane holds" if lanes else ""))
            return
        if time.monotonic() >= next_report:
            next_report += PROGRESS_EVERY_S
            launcher.say("calibrate", f"{hb.counts.get('distance_dm', 0) / 10:.0f} m, "
                                      f"{hb.counts.get('driven_ds', 0) / 10:.0f} s")
    estop = EStop(engaged=True, reason="calibration drive stopped (Ctrl-C)")
    estop.header.stamp_ns = time.time_ns()
    key = key_for("estop", monitor.robot)
    for _ in range(3):
        monitor.session.put(key, encode(estop))
        time.sleep(ESTOP_HOLD_S / 3)
    launcher.say("calibrate", "stopped: e-stop engaged, the stack stops")
