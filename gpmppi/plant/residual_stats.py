"""One-step residuals of the nominal model on driving data, and how they differ between terrains.

The residual of tick k is the measured velocity at t_{k+1} minus `velocity_step_exact` from the
measured velocity at t_k under the command of tick k: the GP's training target. Patterns are the
mean residuals in bins of the command (v_ref x omega_ref); two terrains differ clearly when their bin
means differ by many standard errors (`pattern_separation`), not merely in noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpmppi.models.dynamic_unicycle import velocity_step_exact
from gpmppi.models.identify import identify_theta
from gpmppi.plant.excitation import TerrainRun

V_REF_EDGES = np.array([0.0, 0.7, 1.4, 2.0001])
W_REF_EDGES = np.array([-np.pi - 1e-9, -1.0, -0.3, 0.3, 1.0, np.pi + 1e-9])
# moderate driving (hand-driven logs usually stay here): v_ref <= 1.7, |omega_ref| <= 1.5, v <= 1.5, |omega| <= 1.5
MODERATE_BOX_HI = np.array([1.7, 1.5, 1.5, 1.5])


@dataclass
class ResidualStats:
    terrain: str
    n: int
    rms: np.ndarray  # (2,) [v, omega]
    mean: np.ndarray  # (2,)
    rms_moderate: np.ndarray  # (2,) restricted to moderate driving (MODERATE_BOX_HI)
    n_moderate: int
    bin_mean: np.ndarray  # (B, 2) mean residual per command bin (NaN where empty)
    bin_sem: np.ndarray  # (B, 2) standard error of that mean
    bin_count: np.ndarray  # (B,)


def one_step_residuals(theta: np.ndarray, runs: list[TerrainRun]) -> tuple[np.ndarray, np.ndarray]:
    """GP inputs (n, 4) `[v_ref, omega_ref, v, omega]` and residual targets (n, 2) over all runs."""
    xs, ys = [], []
    for run in runs:
        s, c = run.state, run.command
        pv, pw = velocity_step_exact(theta, s[:-1, 3].copy(), s[:-1, 4].copy(), c[:-1, 0].copy(),
                                     c[:-1, 1].copy(), run.dt)
        xs.append(np.column_stack([c[:-1, 0], c[:-1, 1], s[:-1, 3], s[:-1, 4]]))
        ys.append(np.column_stack([s[1:, 3] - pv, s[1:, 4] - pw]))
    return np.vstack(xs), np.vstack(ys)


def theta_from_runs(runs: list[TerrainRun]) -> np.ndarray:
    """Identify theta on several runs (each its own segment)."""
    return identify_theta([r.state[:, 3] for r in runs], [r.state[:, 4] for r in runs],
                          [r.command[:, 0] for r in runs], [r.command[:, 1] for r in runs], runs[0].dt)


def residual_stats(theta: np.ndarray, terrain: str, runs: list[TerrainRun]) -> ResidualStats:
    x, y = one_step_residuals(theta, runs)
    box = np.all(np.abs(x) <= MODERATE_BOX_HI, axis=1)
    iv = np.clip(np.searchsorted(V_REF_EDGES, x[:, 0], side="right") - 1, 0, len(V_REF_EDGES) - 2)
    iw = np.clip(np.searchsorted(W_REF_EDGES, x[:, 1], side="right") - 1, 0, len(W_REF_EDGES) - 2)
    b = iv * (len(W_REF_EDGES) - 1) + iw
    n_bins = (len(V_REF_EDGES) - 1) * (len(W_REF_EDGES) - 1)
    count = np.bincount(b, minlength=n_bins)
    mean = np.full((n_bins, 2), np.nan)
    sem = np.full((n_bins, 2), np.nan)
    for k in np.flatnonzero(count > 1):
        mean[k] = y[b == k].mean(axis=0)
        sem[k] = y[b == k].std(axis=0, ddof=1) / np.sqrt(count[k])
    return ResidualStats(
        terrain=terrain,
        n=len(y),
        rms=np.sqrt(np.mean(y**2, axis=0)),
        mean=y.mean(axis=0),
        rms_moderate=np.sqrt(np.mean(y[box] ** 2, axis=0)) if box.any() else np.full(2, np.nan),
        n_moderate=int(box.sum()),
        bin_mean=mean,
        bin_sem=sem,
        bin_count=count,
    )


def pattern_separation(a: ResidualStats, b: ResidualStats, min_count: int = 30) -> np.ndarray:
    """(2,) RMS over shared bins of the bin-mean difference in standard errors, for v and omega.

    About 1 when the two terrains have the same mean residual pattern (differences are noise);
    much larger when the patterns differ.
    """
    shared = (a.bin_count >= min_count) & (b.bin_count >= min_count)
    if not shared.any():
        return np.full(2, np.nan)
    z = (a.bin_mean[shared] - b.bin_mean[shared]) / np.sqrt(a.bin_sem[shared] ** 2 + b.bin_sem[shared] ** 2)
    return np.sqrt(np.mean(z**2, axis=0))
