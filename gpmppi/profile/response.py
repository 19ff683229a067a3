"""Each terrain's velocity response to a command: a steady-state map and a first-order rate.

Why the terrain estimator needs it: the GP's input `[v_ref, omega_ref, v, omega]` lacks the plant's hidden states
(wheel speeds, the motor drivers' filtered setpoints, the PI integrators), so at a held command the true
terrain's own GP is off by up to 0.02 rad/s a step, as much as the terrains differ from each other
(docs/terrain_identification.md, "Smooth commands"). Under smooth commands the robot drives close to steady
state, and the one-step GP evidence then points at the wrong terrain. A terrain's steady response to a held
command does not have that problem: it is measured directly, by holding each command of a grid until the
velocities settle.

The model per terrain i and output c (v, omega):

    p_{k+1} = p_k + rate_i,c (S_i,c(u_k) - p_k)

with `S_i` the steady (v, omega) reached under the held command u, bilinear on a (v_ref, omega_ref) grid, and
`rate` the one-step approach to it, fitted by least squares on excitation drives. Run free from a measured
velocity, `p` is the velocity terrain i would give under the commands applied since; it is unbiased at steady
state by construction, while its error in fast transients (a first-order stand-in for a higher-order plant)
averages out over a second or two.

File form (YAML, written by `gpmppi evaluate terrain-response`):

    version: 1
    v_ref: [...]          # grid of held forward-speed commands [m/s], increasing
    omega_ref: [...]      # grid of held yaw-rate commands [rad/s], increasing
    terrains:
      asphalt: {rate: [r_v, r_omega], v: [[...], ...], omega: [[...], ...]}   # (len v_ref, len omega_ref) each
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

SHIPPED_RESPONSE = Path(__file__).resolve().parents[1] / "data" / "terrain_response.yaml"
FIT_COMMAND = "gpmppi evaluate terrain-response"


@dataclass(frozen=True)
class TerrainResponse:
    """Steady-state maps and rates of a set of terrains, on one command grid."""

    v_ref: np.ndarray  # (A,) held forward-speed commands of the grid [m/s], increasing
    omega_ref: np.ndarray  # (B,) held yaw-rate commands of the grid [rad/s], increasing
    terrains: tuple[str, ...]  # (M,) names
    steady: np.ndarray  # (M, A, B, 2) steady (v [m/s], omega [rad/s]) under each held command
    rate: np.ndarray  # (M, 2) one-step approach rate to the steady state (v, omega), in (0, 1]

    def __post_init__(self) -> None:
        a, b, m = len(self.v_ref), len(self.omega_ref), len(self.terrains)
        if a < 2 or b < 2 or np.any(np.diff(self.v_ref) <= 0) or np.any(np.diff(self.omega_ref) <= 0):
            raise ValueError("terrain response: v_ref and omega_ref must each be >= 2 increasing numbers")
        if self.steady.shape != (m, a, b, 2) or not np.all(np.isfinite(self.steady)):
            raise ValueError(f"terrain response: steady must be finite of shape {(m, a, b, 2)}, got "
                             f"{self.steady.shape}")
        if self.rate.shape != (m, 2) or not np.all((self.rate > 0) & (self.rate <= 1)):
            raise ValueError(f"terrain response: every rate must lie in (0, 1], got {self.rate.tolist()}")

    def select(self, names: list[str], source: str = "terrain response") -> TerrainResponse:
        """The same model for `names` in that order (the GP model's terrains); an error names any missing one."""
        missing = [t for t in names if t not in self.terrains]
        if missing:
            raise ValueError(f"{source}: no response for terrain(s) {missing} (have {list(self.terrains)}); fit them "
                             f"with `{FIT_COMMAND}`, or set response: none")
        idx = [self.terrains.index(t) for t in names]
        return TerrainResponse(self.v_ref, self.omega_ref, tuple(names), self.steady[idx], self.rate[idx])

    def covers(self, command: np.ndarray) -> bool:
        """Whether the held `command` (2,) lies on the measured grid (off it `steady_at` clamps, so it is wrong by as
        much as the command lies beyond the grid)."""
        return bool(self.v_ref[0] <= command[0] <= self.v_ref[-1]
                    and self.omega_ref[0] <= command[1] <= self.omega_ref[-1])

    def steady_at(self, command: np.ndarray) -> np.ndarray:
        """(M, 2) every terrain's steady (v, omega) under the held `command` (2,), bilinear; clamped to the grid."""
        v = float(np.clip(command[0], self.v_ref[0], self.v_ref[-1]))
        w = float(np.clip(command[1], self.omega_ref[0], self.omega_ref[-1]))
        i = min(int(np.searchsorted(self.v_ref, v, side="right")) - 1, len(self.v_ref) - 2)
        j = min(int(np.searchsorted(self.omega_ref, w, side="right")) - 1, len(self.omega_ref) - 2)
        fv = (v - self.v_ref[i]) / (self.v_ref[i + 1] - self.v_ref[i])
        fw = (w - self.omega_ref[j]) / (self.omega_ref[j + 1] - self.omega_ref[j])
        s = self.steady
        return ((1 - fv) * (1 - fw) * s[:, i, j] + fv * (1 - fw) * s[:, i + 1, j]
                + (1 - fv) * fw * s[:, i, j + 1] + fv * fw * s[:, i + 1, j + 1])

    def step(self, predicted: np.ndarray, command: np.ndarray) -> np.ndarray:
        """(M, 2) each terrain's velocity one step on from `predicted` (M, 2) under `command` (2,)."""
        return predicted + self.rate * (self.steady_at(command) - predicted)

    def to_yaml(self, header: str = "") -> str:
        body = {
            "version": 1,
            "v_ref": [round(float(x), 4) for x in self.v_ref],
            "omega_ref": [round(float(x), 4) for x in self.omega_ref],
            "terrains": {
                t: {"rate": [round(float(x), 4) for x in self.rate[i]],
                    "v": np.round(self.steady[i, :, :, 0], 4).tolist(),
                    "omega": np.round(self.steady[i, :, :, 1], 4).tolist()}
                for i, t in enumerate(self.terrains)
            },
        }
        return header + yaml.safe_dump(body, sort_keys=False, default_flow_style=None, width=200)


def load_response(path: Path | str = SHIPPED_RESPONSE) -> TerrainResponse:
    """A terrain response file (see the module docstring); a clear error naming the file when it is malformed."""
    try:
        # libyaml's scanner where PyYAML has it: the same values (the constructor is the same Python code) in 7 ms
        # instead of 52 ms of CPU for the shipped file, which every terrain estimator (each terrain service's start,
        # each closed loop with an estimator) reads
        data = yaml.load(Path(path).read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
        v_ref = np.asarray(data["v_ref"], dtype=np.float64)
        omega_ref = np.asarray(data["omega_ref"], dtype=np.float64)
        names = tuple(str(t) for t in data["terrains"])
        steady = np.stack([np.stack([np.asarray(e["v"], dtype=np.float64), np.asarray(e["omega"], dtype=np.float64)],
                                    axis=-1) for e in data["terrains"].values()])
        rate = np.array([[float(x) for x in e["rate"]] for e in data["terrains"].values()], dtype=np.float64)
        return TerrainResponse(v_ref, omega_ref, names, steady, rate)
    except (OSError, KeyError, TypeError, IndexError, ValueError, AttributeError, yaml.YAMLError) as e:
        raise ValueError(f"terrain response file {path}: {e} (expected version, v_ref, omega_ref and per terrain "
                         f"rate, v, omega; write one with `{FIT_COMMAND}`)") from e

