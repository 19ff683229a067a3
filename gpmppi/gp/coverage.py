"""Which part of the planner's range a ground's training data covers, and whether that is enough to fit.

The planner commands v_ref in [0, 2] m/s and omega_ref in [-pi, pi] rad/s (DESIGN.md); a GP knows a ground only
where it was driven. For each ground the fit reports, on a grid over that range, how many one-step samples each cell
holds (commands, and the measured state), how many held commands the log has (a command kept for a second or more:
the steady responses the terrain estimator needs), names the thin cells so the user knows what to drive, and refuses
a ground with too little data, or a logged ground with no held command at all (too little excitation for the terrain
calibration, before the GP is fitted; the calibration fit itself then refuses too few, `CalibrationDataError`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

V_EDGES = np.linspace(0.0, 2.0, 5)  # m/s: four cells of 0.5
W_EDGES = np.linspace(-np.pi, np.pi, 7)  # rad/s: six cells of about 1.05
MIN_PER_CELL = 10  # samples for a cell to count as covered
MIN_SAMPLES = 100  # fewer one-step samples of a ground: refused
MIN_COVERED = 0.15  # a smaller fraction of the command cells covered: refused (the paper's 300 rows cover 25 %)
HOLD_S = 1.0  # a command kept this long counts as held


@dataclass(frozen=True)
class GroundCoverage:
    """One ground's coverage of the planner's command and state range."""

    terrain: str
    samples: int
    command_cells: np.ndarray  # (4, 6) sample counts over (v_ref, omega_ref) cells
    state_cells: np.ndarray  # (4, 6) sample counts over the measured (v, omega) cells
    held: int | None  # held commands in the log (None: the data has no time series, e.g. a residual CSV)

    @property
    def command_covered(self) -> float:
        return float(np.mean(self.command_cells >= MIN_PER_CELL))

    @property
    def state_covered(self) -> float:
        return float(np.mean(self.state_cells >= MIN_PER_CELL))

    def thin(self) -> list[str]:
        """The command cells with fewer than MIN_PER_CELL samples, as ranges to drive."""
        out = []
        for i, j in zip(*np.nonzero(self.command_cells < MIN_PER_CELL), strict=True):
            out.append(f"v_ref {V_EDGES[i]:.1f}-{V_EDGES[i + 1]:.1f} m/s with omega_ref "
                       f"{W_EDGES[j]:+.1f}..{W_EDGES[j + 1]:+.1f} rad/s")
        return out

    def problem(self, min_samples: int = MIN_SAMPLES, min_covered: float = MIN_COVERED) -> str | None:
        """Why this ground cannot be fitted (what to drive), or None."""
        if self.samples < min_samples:
            return (f"ground {self.terrain!r}: {self.samples} one-step samples, at least {min_samples} are needed; "
                    f"drive it longer (loops and figure-eights at 0.5-1.5 m/s, turning both ways)")
        if self.command_covered < min_covered:
            return (f"ground {self.terrain!r}: its commands cover {self.command_covered:.0%} of the planner's range "
                    f"(v_ref 0-2 m/s, |omega_ref| up to pi rad/s), at least {min_covered:.0%} is needed; drive "
                    f"{'; '.join(self.thin()[:3])}")
        if self.held == 0:
            return (f"ground {self.terrain!r}: no command held {HOLD_S:g} s or longer, too little excitation for the "
                    "terrain calibration's steady response; drive it more: hold commands for >= 3 s at speeds 0-2 m/s "
                    "and turn rates -3..3 rad/s, both ways")
        return None


def cells(v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Sample counts over the (v, omega) grid; values outside the range count in the edge cells."""
    i = np.clip(np.searchsorted(V_EDGES, v, side="right") - 1, 0, len(V_EDGES) - 2)
    j = np.clip(np.searchsorted(W_EDGES, w, side="right") - 1, 0, len(W_EDGES) - 2)
    counts = np.zeros((len(V_EDGES) - 1, len(W_EDGES) - 1), dtype=np.int64)
    np.add.at(counts, (i, j), 1)
    return counts


def held_commands(v_ref: np.ndarray, w_ref: np.ndarray, seg: np.ndarray, dt: float, hold_s: float = HOLD_S) -> int:
    """Runs of one unchanged command lasting `hold_s` or more within a segment."""
    if len(v_ref) == 0:
        return 0
    changed = np.ones(len(v_ref), dtype=bool)
    changed[1:] = (np.abs(np.diff(v_ref)) > 1e-6) | (np.abs(np.diff(w_ref)) > 1e-6) | (np.diff(seg) != 0)
    starts = np.flatnonzero(changed)
    lengths = np.diff(np.append(starts, len(v_ref)))
    return int(np.sum(lengths * dt >= hold_s - 1e-9))


def ground_coverage(terrain: str, x: np.ndarray, held: int | None = None) -> GroundCoverage:
    """Coverage of one ground's one-step inputs x (N, 4) = [v_ref, omega_ref, v, omega]."""
    x = np.asarray(x, dtype=np.float64).reshape(-1, 4)
    return GroundCoverage(terrain, len(x), cells(x[:, 0], x[:, 1]), cells(x[:, 2], x[:, 3]), held)
