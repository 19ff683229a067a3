"""The one reader of recorded logs: a recording's ticks, each state paired with the command in force and its ground.

`read_log_runs` holds the pairing rule and the label handling; its two views are the per-ground runs
(`runs_by_ground`: `tools.dataset.read_dataset`, `gpmppi dataset-stats`, `calibrate drive --resume`, the terrain
calibration) and the trainer's per-ground series (`series_of_runs`: `tools.train_data.read_log_series`, `gpmppi
train`). It reads a `gpmppi dataset` file, a calibration drive (`gpmppi calibrate drive`), a stack recording
(`gpmppi launch --record`) or a robot's own log with state + cmd.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # imported where used: the command tree is built without numba (gpmppi.plant loads it)
    from gpmppi.plant.excitation import TerrainRun

NS = 1_000_000_000
COMMAND_BOUND_TICKS = 2.0  # a command older than this many dt at a state's stamp is no longer in force
TICK_TOLERANCE = 0.25  # the next tick is the state nearest one dt on, within this fraction of dt
_TOPICS = {"state": "state", "cmd": "cmd", "terrain/label": "label"}  # key suffix -> what it holds


class DataError(ValueError):
    """Training or prediction data that cannot be used; the message says what, where, and what to do."""


def _read_messages(path: Path, robot: str | None) -> tuple[str, dict[str, dict]]:
    """(robot, {"state": stamp -> [x, y, theta, v, omega], "cmd": stamp -> [v_ref, omega_ref], "label": stamp ->
    name}) of one robot's messages (`robot` None: the one robot whose state and cmd the log holds)."""
    from services.recording.mcap_io import read_messages

    keys = None if robot is None else [f"gpmppi/{robot}/{suffix}" for suffix in _TOPICS]
    found: dict[str, dict[str, dict]] = {}
    try:
        for key, _, msg in read_messages(path, keys=keys):
            parts = key.split("/", 2)
            if len(parts) < 3 or parts[0] != "gpmppi" or parts[2] not in _TOPICS:
                continue
            into = found.setdefault(parts[1], {"state": {}, "cmd": {}, "label": {}})[_TOPICS[parts[2]]]
            stamp = msg.header.stamp_ns
            if parts[2] == "state":
                into[stamp] = msg.as_array()
            elif parts[2] == "cmd":
                into[stamp] = [msg.v_ref, msg.omega_ref]
            else:
                into[stamp] = msg.terrain
    except FileNotFoundError as e:
        raise DataError(str(e)) from None
    except Exception as e:  # noqa: BLE001 - any reader failure means the file is not a usable log
        raise DataError(f"{path}: not a readable MCAP log ({type(e).__name__}: {e})") from e
    robots = sorted(r for r, m in found.items() if m["state"] and m["cmd"])
    if robot is None:
        if len(robots) != 1:
            raise DataError(f"{path}: expected state and cmd of one robot, found robots {robots}; pass --robot")
        robot = robots[0]
    if robot not in robots:
        held = [f"gpmppi/{r}/state" for r in sorted(found) if found[r]["state"]]
        if keys is not None and not held:  # only this robot's keys were read: name the others from the channels
            held = _state_keys(path)
        raise DataError(f"{path}: no state + cmd messages for robot {robot!r} (gpmppi/{robot}/state); the log holds "
                        f"{held or 'no gpmppi/<robot>/state keys'}: wrong --robot? pass --robot NAME")
    return robot, found[robot]


def _state_keys(path: Path) -> list[str]:
    """The log's gpmppi/<robot>/state channels (from the channel list: nothing is decoded)."""
    from mcap.reader import make_reader

    from services.recording.mcap_io import recording_files

    keys: set[str] = set()
    for part in recording_files(path) or [path]:
        with open(part, "rb") as f:
            summary = make_reader(f).get_summary()
        if summary is not None:
            keys |= {c.topic for c in summary.channels.values()}
    return sorted(k for k in keys if k.startswith("gpmppi/") and k.endswith("/state") and k.count("/") == 2)


def read_log_runs(path: str | Path, dt: float = 0.1, terrain: str | None = None,
                  robot: str | None = None) -> list[TerrainRun]:
    """The contiguous runs of dt ticks of one robot's recording, in time order (`robot` None: the one robot whose
    state and cmd the log holds).

    The pairing rule: each state is paired with the command in force over the interval that follows it, the latest
    command stamped at or before the state's stamp, if that command is at most COMMAND_BOUND_TICKS dt older than the
    state; a state with no such command is left out. In a dataset file every state has its command on its own stamp;
    in the stack a command carries the stamp of the state it was planned from (or, from another source, its own
    later stamp: then the state pairs with the command before, the one the base still held). The label is the
    latest at or before the state's stamp (`terrain` when the recording has none; required then).

    Ticks: from a run's first state, each next tick is the state nearest one dt later, within TICK_TOLERANCE dt
    (odometry faster than 1 / dt is thinned to dt ticks; jitter is tolerated). Where there is none (a lost or late
    state), or a state has no command in force, or the label changes, the run ends and a new one starts at the
    next usable state. `TerrainRun.time` holds the ticks' own stamps (seconds since the run's first). A dataset
    file reads as it was written, tick for tick. Errors (no such robot, no labels and no `terrain`, nothing
    paired, not a log) are `DataError`s of one line.
    """
    from gpmppi.plant.excitation import TerrainRun

    path = Path(path)
    robot, msgs = _read_messages(path, robot)
    states, commands, labels = msgs["state"], msgs["cmd"], msgs["label"]
    if not labels and terrain is None:
        raise DataError(f"{path}: the log has no terrain labels; name the terrain with --terrain NAME")
    cmd_stamps = np.array(sorted(commands), dtype=np.int64)
    label_stamps = np.array(sorted(labels), dtype=np.int64)
    state_stamps = np.array(sorted(states), dtype=np.int64)
    bound = int(round(COMMAND_BOUND_TICKS * dt * NS))
    step, tol = int(round(dt * NS)), int(round(TICK_TOLERANCE * dt * NS))
    # (state stamp, command stamp, label, whether a run starts here)
    ticks: list[tuple[int, int, str, bool]] = []
    i, fresh = 0, True
    while i < len(state_stamps):
        stamp = int(state_stamps[i])
        c = int(np.searchsorted(cmd_stamps, stamp, side="right")) - 1
        lab = int(np.searchsorted(label_stamps, stamp, side="right")) - 1
        name = labels[int(label_stamps[lab])] if lab >= 0 else terrain
        if c >= 0 and stamp - int(cmd_stamps[c]) <= bound and name is not None:
            ticks.append((stamp, int(cmd_stamps[c]), name, fresh))
            fresh = False
        else:
            fresh = True
        # the next tick: the state nearest one dt on, within the tolerance; none there: a new run from the next state
        target = stamp + step
        lo = int(np.searchsorted(state_stamps, target - tol, side="left"))
        hi = int(np.searchsorted(state_stamps, target + tol, side="right"))
        if lo < hi:
            i = lo + int(np.argmin(np.abs(state_stamps[lo:hi] - target)))
        else:
            i, fresh = hi, True
    if not ticks:
        raise DataError(f"{path}: no state has a command in force on {robot!r} (are the stamps in nanoseconds?)")
    runs: list[TerrainRun] = []
    start = 0
    for i in range(1, len(ticks) + 1):
        if i < len(ticks):
            gap = (ticks[i][0] - ticks[i - 1][0]) / NS > 1.5 * dt
            if not (gap or ticks[i][3] or ticks[i][2] != ticks[i - 1][2]):
                continue
        chunk = ticks[start:i]
        st = np.array([states[s] for s, _, _, _ in chunk])
        t = (np.array([s for s, _, _, _ in chunk]) - chunk[0][0]) / NS
        runs.append(TerrainRun(chunk[0][2], dt, t, st, np.array([commands[c] for _, c, _, _ in chunk]), st.copy()))
        start = i
    return runs


def runs_by_ground(runs: list[TerrainRun]) -> dict[str, list[TerrainRun]]:
    """Ground -> its runs in time order (grounds in the order they were first driven)."""
    out: dict[str, list[TerrainRun]] = {}
    for r in runs:
        out.setdefault(r.terrain, []).append(r)
    return out


def series_of_runs(runs: list[TerrainRun]) -> dict[str, dict[str, np.ndarray]]:
    """The trainer's per-ground series: ground -> {"v", "w", "v_ref", "w_ref", "seg", "x", "y", "yaw"}, one value
    a tick; "seg" numbers the runs 1, 2, ... in time order over all grounds (a one-step pair never spans two)."""
    out: dict[str, dict[str, list[np.ndarray]]] = {}
    for seg, r in enumerate(runs, start=1):
        into = out.setdefault(r.terrain, {k: [] for k in ("v", "w", "v_ref", "w_ref", "seg", "x", "y", "yaw")})
        for k, a in (("v", r.state[:, 3]), ("w", r.state[:, 4]), ("v_ref", r.command[:, 0]),
                     ("w_ref", r.command[:, 1]), ("seg", np.full(len(r.command), seg)), ("x", r.state[:, 0]),
                     ("y", r.state[:, 1]), ("yaw", r.state[:, 2])):
            into[k].append(a)
    return {name: {k: np.concatenate(parts) for k, parts in s.items()} for name, s in out.items()}
