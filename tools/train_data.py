"""`gpmppi train`'s data: a residual CSV's columns (`read_csv_columns`, `csv_inputs`, `csv_residuals`) and the
per-ground series of MCAP logs (`read_log_series`, `read_logs_series`); `DataError` for data that cannot be read."""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

import numpy as np

from tools.log_reader import DataError

__all__ = ["DataError", "csv_inputs", "csv_residuals", "is_mcap", "read_csv_columns", "read_log_series",
           "read_logs_series"]

INPUT_COLUMNS = ("cmd_lin", "cmd_ang", "curr_lin", "curr_ang")
PAPER_PREFIX = "gp_ip_"
_TARGET_RE = re.compile(r"^(?P<terrain>.+)_(?P<out>Lin|Ang)_Error$", re.IGNORECASE)


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


# ---- MCAP ----------------------------------------------------------------------------------------
def read_log_series(path: Path, dt: float, terrain: str | None, robot: str | None) -> dict[str, dict]:
    """terrain -> {"v", "w", "v_ref", "w_ref", "seg", "x", "y", "yaw"} series of dt ticks from a recorded log: the
    runs of `tools.log_reader.read_log_runs` (its docstring holds the pairing rule and the labels), one segment
    each, numbered in time order over all grounds (`series_of_runs`)."""
    from tools.log_reader import read_log_runs, series_of_runs

    return series_of_runs(read_log_runs(path, dt, terrain, robot))


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
