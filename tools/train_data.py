"""`gpmppi train`'s data: a residual CSV's columns (`read_csv_columns`, `csv_inputs`, `csv_residuals`) and the
per-ground series of MCAP logs (`read_log_series`, `read_logs_series`); `DataError` for data that cannot be read."""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

import numpy as np

INPUT_COLUMNS = ("cmd_lin", "cmd_ang", "curr_lin", "curr_ang")
PAPER_PREFIX = "gp_ip_"
_TARGET_RE = re.compile(r"^(?P<terrain>.+)_(?P<out>Lin|Ang)_Error$", re.IGNORECASE)


class DataError(ValueError):
    """Training or prediction data that cannot be used; the message says what, where, and what to do."""


MCAP_MAGIC = b"\x89MCAP0\r\n"


def is_mcap(path: Path) -> bool:
    """True when the file starts with MCAP's magic bytes."""
    with open(path, "rb") as f:
        return f.read(len(MCAP_MAGIC)) == MCAP_MAGIC


# ---- CSV ----------------------------------------------------------------------------------------
def read_csv_columns(path: Path) -> dict[str, np.ndarray]:
    """All columns of a numeric CSV as float arrays; errors name the file, row and column."""
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    with open(path, newline="") as f:
        reader = csv.reader(f)
        try:
            header = next(reader)
        except StopIteration:
            raise DataError(f"{path}: empty file (expected a header row)") from None
        header = [h.strip() for h in header]
        rows: list[list[float]] = []
        for line_no, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise DataError(f"{path}:{line_no}: {len(row)} fields, the header has {len(header)}")
            values = []
            for name, cell in zip(header, row, strict=True):
                try:
                    value = float(cell)
                except ValueError:
                    raise DataError(f"{path}:{line_no}: column {name!r} holds {cell!r}, not a number") from None
                if not math.isfinite(value):
                    raise DataError(
                        f"{path}:{line_no}: column {name!r} is {cell!r} (NaN/inf); remove or fix that row"
                    )
                values.append(value)
            rows.append(values)
    if not rows:
        raise DataError(f"{path}: no data rows after the header")
    data = np.asarray(rows, dtype=np.float64)
    return {name: data[:, i] for i, name in enumerate(header)}


def csv_inputs(cols: dict[str, np.ndarray], path: Path) -> np.ndarray:
    """The (N, 4) GP inputs from `cmd_lin,cmd_ang,curr_lin,curr_ang` (or the paper's `gp_ip_*` names)."""
    out = []
    for name in INPUT_COLUMNS:
        if name in cols:
            out.append(cols[name])
        elif PAPER_PREFIX + name in cols:
            out.append(cols[PAPER_PREFIX + name])
        else:
            raise DataError(
                f"{path}: missing input column {name!r} (or {PAPER_PREFIX + name!r}); "
                f"columns present: {sorted(cols)}"
            )
    return np.column_stack(out)


def csv_residuals(cols: dict[str, np.ndarray], path: Path) -> dict[str, np.ndarray]:
    """terrain (lower case) -> (N, 2) residual targets from `{Terrain}_{Lin,Ang}_Error` columns."""
    found: dict[str, dict[str, np.ndarray]] = {}
    for name, values in cols.items():
        m = _TARGET_RE.match(name)
        if m:
            found.setdefault(m["terrain"].lower(), {})[m["out"].lower()] = values
    if not found:
        raise DataError(f"{path}: no residual columns named like 'Asphalt_Lin_Error' / 'Asphalt_Ang_Error'")
    out = {}
    for t, parts in found.items():
        if set(parts) != {"lin", "ang"}:
            missing = "Ang" if "lin" in parts else "Lin"
            raise DataError(f"{path}: terrain {t!r} has no {missing}_Error column")
        out[t] = np.column_stack([parts["lin"], parts["ang"]])
    return out


# ---- MCAP ---------------------------------------------------------------------------------------
def read_log_series(path: Path, dt: float, terrain: str | None, robot: str | None) -> dict[str, dict]:
    """terrain -> {"v", "w", "v_ref", "w_ref", "seg", "x", "y", "yaw"} series on a dt grid from a recorded log.

    Ticks are the state stamps resampled every dt (the grid restarts at the next state where a tick has none);
    the command over [t_k, t_k + dt) is the last one stamped at or before t_k (+dt/4 for clock jitter) and at most
    2 dt old; a terrain label the same. A segment ends where a tick is missing, the command is stale, or the label
    changes.
    """
    from services.recording.mcap_io import read_messages

    states: dict[str, list[tuple[int, float, float, float, float, float]]] = {}
    cmds: dict[str, list[tuple[int, float, float]]] = {}
    labels: dict[str, list[tuple[int, str]]] = {}
    try:
        for key, _, msg in read_messages(path):
            parts = key.split("/")
            if len(parts) < 3 or parts[0] != "gpmppi":
                continue
            rob, rest = parts[1], "/".join(parts[2:])
            stamp = msg.header.stamp_ns
            if rest == "state":
                states.setdefault(rob, []).append((stamp, msg.v, msg.omega, msg.x, msg.y, msg.theta))
            elif rest == "cmd":
                cmds.setdefault(rob, []).append((stamp, msg.v_ref, msg.omega_ref))
            elif rest == "terrain/label":
                labels.setdefault(rob, []).append((stamp, msg.terrain))
    except FileNotFoundError as e:
        raise DataError(str(e)) from None
    except Exception as e:  # noqa: BLE001 - any reader failure means the file is not a usable log
        raise DataError(f"{path}: not a readable MCAP log ({type(e).__name__}: {e})") from e
    robots = sorted(set(states) & set(cmds))
    if robot is None:
        if len(robots) != 1:
            raise DataError(f"{path}: expected state and cmd of one robot, found robots {robots}; pass --robot")
        robot = robots[0]
    if robot not in robots:
        found = [f"gpmppi/{r}/state" for r in sorted(states)]
        raise DataError(f"{path}: no state + cmd messages for robot {robot!r} (gpmppi/{robot}/state); the log holds "
                        f"{found or 'no gpmppi/<robot>/state keys'}; pass --robot NAME")
    st = np.array(sorted(states[robot]))
    cm = np.array(sorted(cmds[robot]))
    lab = sorted(labels.get(robot, []))
    if not lab and terrain is None:
        raise DataError(f"{path}: the log has no terrain labels; name the terrain with --terrain NAME")
    dt_ns = int(round(dt * 1e9))
    tol = dt_ns // 4
    t_state = st[:, 0].astype(np.int64)
    t_cmd = cm[:, 0].astype(np.int64)
    t_lab = np.array([s for s, _ in lab], dtype=np.int64)
    out: dict[str, dict[str, list]] = {}
    seg_id = 0
    prev: tuple[int, str] | None = None  # (tick index, terrain) of the previous usable tick
    tick = -1
    t = int(t_state[0]) - dt_ns
    while True:
        tick += 1
        t += dt_ns
        i = int(np.searchsorted(t_state, t))
        if i >= len(t_state) and t - int(t_state[-1]) > tol:
            break
        cand = [j for j in (i - 1, i) if 0 <= j < len(t_state)]
        j = min(cand, key=lambda j: abs(int(t_state[j]) - t))
        if abs(int(t_state[j]) - t) > tol:
            # no state on this tick (a pause, a late start): the grid restarts at the next state, so the states
            # after a gap that is not a whole number of ticks are still on it
            nxt = int(np.searchsorted(t_state, t + tol, side="right"))
            if nxt >= len(t_state):
                break
            prev = None
            t = int(t_state[nxt]) - dt_ns
            continue
        c = int(np.searchsorted(t_cmd, t + tol, side="right")) - 1
        name = terrain
        if lab:
            li = int(np.searchsorted(t_lab, t + tol, side="right")) - 1
            name = lab[li][1] if li >= 0 else None
        ok = abs(int(t_state[j]) - t) <= tol and c >= 0 and t - int(t_cmd[c]) <= 2 * dt_ns and name is not None
        if not ok:
            prev = None
            continue
        if prev is None or prev[0] != tick - 1 or prev[1] != name:
            seg_id += 1
        series = out.setdefault(name, {"v": [], "w": [], "v_ref": [], "w_ref": [], "seg": [], "x": [], "y": [],
                                       "yaw": []})
        series["v"].append(st[j, 1])
        series["w"].append(st[j, 2])
        series["x"].append(st[j, 3])
        series["y"].append(st[j, 4])
        series["yaw"].append(st[j, 5])
        series["v_ref"].append(cm[c, 1])
        series["w_ref"].append(cm[c, 2])
        series["seg"].append(seg_id)
        prev = (tick, name)
    if not out:
        raise DataError(f"{path}: no state/command pairs on a {dt} s grid (are the stamps in nanoseconds?)")
    return {t: {k: np.asarray(v) for k, v in s.items()} for t, s in out.items()}


# ---- the command --------------------------------------------------------------------------------
def read_logs_series(paths: list[Path], dt: float, terrain: str | None, robot: str | None) -> dict[str, dict]:
    """`read_log_series` of every log, each ground's series concatenated in the order given (a calibration drive is
    one log per ground and run: stopped and resumed, or one ground at a time). Segment ids are kept apart across
    logs, so no one-step pair spans two logs."""
    merged: dict[str, dict[str, list[np.ndarray]]] = {}
    next_seg = 0
    for path in paths:
        series = read_log_series(path, dt, terrain, robot)
        top = next_seg
        for name, s in series.items():
            into = merged.setdefault(name, {k: [] for k in s})
            for k, a in s.items():
                into[k].append(a + next_seg if k == "seg" else a)
            top = max(top, next_seg + int(np.max(s["seg"])) + 1)
        next_seg = top
    return {name: {k: np.concatenate(parts) for k, parts in s.items()} for name, s in merged.items()}
