"""The paper's simulated plant: the nominal dynamic unicycle plus a residual network per terrain.

Each 0.1 s step: the nominal velocity ODE is integrated under the constant command (RK4, fine
substeps), then the network's residual for the chosen terrain is added to the final (v, omega),
as in the paper. The pose is integrated alongside with the same substeps, using the nominal
velocities plus the residual ramped linearly over the step (so the path is continuous and
consistent with the velocity at the end of the step).

Network file (JSON): `layers` with `fc1.weight` [32, 4], `fc1.bias`, `fc2.weight` [32, 32],
`fc2.bias`, `fc3.weight` [2M, 32], `fc3.bias` (PyTorch layout, weight is [out, in]) and `scalers`
with `input_mean/input_scale` (4,) and `output_mean/output_scale` (2M,). Input
`[v_ref, omega_ref, v, omega]`; outputs `[T0_v, T0_omega, T1_v, ...]`. Terrain names come from a
top-level `terrains` list if the file has one, else from the caller.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit

from gpmppi.models.dynamic_unicycle import accel

RESIDUAL_DT = 0.1  # [s] the step the residual network was trained for
POSE_SUBSTEPS = 50


class NetworkFileError(ValueError):
    """The residual network file is missing, unreadable or malformed; the message names file and field."""


@dataclass(frozen=True)
class ResidualNet:
    """Weights of Linear(4,H)-tanh-Linear(H,H)-tanh-Linear(H,2M) with input/output standardization."""

    w1: np.ndarray
    b1: np.ndarray
    w2: np.ndarray
    b2: np.ndarray
    w3: np.ndarray
    b3: np.ndarray
    input_mean: np.ndarray
    input_scale: np.ndarray
    output_mean: np.ndarray
    output_scale: np.ndarray
    terrains: list[str] | None = None

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Residuals (n, 2M) for inputs (n, 4) = [v_ref, omega_ref, v, omega] (pure numpy)."""
        z = (np.atleast_2d(x) - self.input_mean) / self.input_scale
        h = np.tanh(z @ self.w1.T + self.b1)
        h = np.tanh(h @ self.w2.T + self.b2)
        return (h @ self.w3.T + self.b3) * self.output_scale + self.output_mean


def load_residual_net(path: str | Path) -> ResidualNet:
    """Read and check a residual network JSON file."""
    file = Path(path)
    try:
        raw = json.loads(file.read_text())
    except OSError as exc:
        raise NetworkFileError(f"{file}: cannot read residual network ({exc.strerror}); check the path") from exc
    except json.JSONDecodeError as exc:
        raise NetworkFileError(f"{file}: not valid JSON: {exc}") from exc

    def field(section: str, key: str) -> np.ndarray:
        try:
            return np.asarray(raw[section][key], dtype=float)
        except (KeyError, TypeError) as exc:
            raise NetworkFileError(f"{file}: missing field {section}.{key}") from exc
        except ValueError as exc:
            raise NetworkFileError(f"{file}: field {section}.{key} is not a numeric array") from exc

    net = ResidualNet(
        *(field("layers", f"fc{i}.{k}") for i in (1, 2, 3) for k in ("weight", "bias")),
        *(field("scalers", k) for k in ("input_mean", "input_scale", "output_mean", "output_scale")),
        terrains=list(raw["terrains"]) if isinstance(raw, dict) and "terrains" in raw else None,
    )
    hidden, n_out = net.w1.shape[0], net.w3.shape[0]
    expected = {
        "layers.fc1.weight": (net.w1.shape, (hidden, 4)),
        "layers.fc1.bias": (net.b1.shape, (hidden,)),
        "layers.fc2.weight": (net.w2.shape, (hidden, hidden)),
        "layers.fc2.bias": (net.b2.shape, (hidden,)),
        "layers.fc3.weight": (net.w3.shape, (n_out, hidden)),
        "layers.fc3.bias": (net.b3.shape, (n_out,)),
        "scalers.input_mean": (net.input_mean.shape, (4,)),
        "scalers.input_scale": (net.input_scale.shape, (4,)),
        "scalers.output_mean": (net.output_mean.shape, (n_out,)),
        "scalers.output_scale": (net.output_scale.shape, (n_out,)),
    }
    for name, (got, want) in expected.items():
        if got != want:
            raise NetworkFileError(f"{file}: field {name} has shape {got}, expected {want}")
    if n_out % 2:
        raise NetworkFileError(f"{file}: {n_out} outputs; expected 2 per terrain (v, omega)")
    if net.terrains is not None and len(net.terrains) != n_out // 2:
        raise NetworkFileError(f"{file}: {len(net.terrains)} terrain names for {n_out // 2} terrains")
    if np.any(net.input_scale <= 0) or np.any(net.output_scale <= 0):
        raise NetworkFileError(f"{file}: scalers.input_scale/output_scale must be positive")
    return net


@njit(cache=True)
def nominal_step_with_pose(
    theta: np.ndarray, x: np.ndarray, v_ref: float, w_ref: float, res_v: float, res_w: float, dt: float, substeps: int
) -> np.ndarray:
    """Nominal velocity ODE plus a linearly ramped residual over dt, with the pose, by RK4 substeps."""
    h = dt / substeps
    px, py, yaw, a, b = x[0], x[1], x[2], x[3], x[4]
    for k in range(substeps):
        t0 = k * h
        # stages: (pose rate from total velocity, nominal velocity rate)
        k1v, k1w = accel(theta, a, b, v_ref, w_ref)
        va, wa = a + res_v * t0 / dt, b + res_w * t0 / dt
        k1x, k1y, k1t = va * math.cos(yaw), va * math.sin(yaw), wa
        a2, b2 = a + 0.5 * h * k1v, b + 0.5 * h * k1w
        k2v, k2w = accel(theta, a2, b2, v_ref, w_ref)
        vb, wb = a2 + res_v * (t0 + 0.5 * h) / dt, b2 + res_w * (t0 + 0.5 * h) / dt
        yb = yaw + 0.5 * h * k1t
        k2x, k2y, k2t = vb * math.cos(yb), vb * math.sin(yb), wb
        a3, b3 = a + 0.5 * h * k2v, b + 0.5 * h * k2w
        k3v, k3w = accel(theta, a3, b3, v_ref, w_ref)
        vc, wc = a3 + res_v * (t0 + 0.5 * h) / dt, b3 + res_w * (t0 + 0.5 * h) / dt
        yc = yaw + 0.5 * h * k2t
        k3x, k3y, k3t = vc * math.cos(yc), vc * math.sin(yc), wc
        a4, b4 = a + h * k3v, b + h * k3w
        k4v, k4w = accel(theta, a4, b4, v_ref, w_ref)
        vd, wd = a4 + res_v * (t0 + h) / dt, b4 + res_w * (t0 + h) / dt
        yd = yaw + h * k3t
        k4x, k4y, k4t = vd * math.cos(yd), vd * math.sin(yd), wd
        px += h / 6.0 * (k1x + 2 * k2x + 2 * k3x + k4x)
        py += h / 6.0 * (k1y + 2 * k2y + 2 * k3y + k4y)
        yaw += h / 6.0 * (k1t + 2 * k2t + 2 * k3t + k4t)
        a += h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
        b += h / 6.0 * (k1w + 2 * k2w + 2 * k3w + k4w)
    out = np.empty(5)
    out[0], out[1], out[2], out[3], out[4] = px, py, yaw, a + res_v, b + res_w
    return out


def _wrap(a: float) -> float:
    w = (a + math.pi) % (2.0 * math.pi) - math.pi
    return math.pi if w == -math.pi else w


class ResidualNetPlant:
    """Nominal dynamic unicycle + the residual network's output for one terrain; the Plant protocol.

    Steps are whole multiples of 0.1 s (the network's step). No sensor noise unless `noise_std`
    (5,) is given, matching the paper's noise-free plant.
    """

    dt = RESIDUAL_DT
    command_period_s = RESIDUAL_DT  # it takes a new command only every network step (`CommandPath.advance`)

    def __init__(
        self,
        path: str | Path,
        theta: np.ndarray,
        terrain: str,
        terrain_names: list[str] | None = None,
        seed: int = 0,
        noise_std: np.ndarray | None = None,
    ) -> None:
        self.net = load_residual_net(path)
        self.theta = np.asarray(theta, dtype=float)
        if self.theta.shape != (6,) or not np.all(np.isfinite(self.theta)) or min(self.theta[0], self.theta[1]) <= 0:
            raise ValueError(f"theta must be 6 finite numbers with theta1, theta2 > 0, got {theta!r}")
        names = self.net.terrains if self.net.terrains is not None else terrain_names
        n_terrains = self.net.w3.shape[0] // 2
        if names is None or len(names) != n_terrains:
            raise ValueError(
                f"{path}: the network has {n_terrains} terrains and no names; pass terrain_names "
                f"with {n_terrains} names in output order (got {names!r})"
            )
        self.terrain_names = [n.lower() for n in names]
        self.seed = seed
        self.noise_std = None if noise_std is None else np.asarray(noise_std, dtype=float)
        self._rng = np.random.default_rng(seed)
        self._index = 0
        self.terrain = ""
        self.set_terrain(terrain)
        self._x = np.zeros(5)

    def set_terrain(self, name: str) -> None:
        key = name.lower()
        if key not in self.terrain_names:
            raise KeyError(f"unknown terrain {name!r}; this network has {self.terrain_names}")
        self._index = self.terrain_names.index(key)
        self.terrain = key

    def reset(self, state: np.ndarray) -> None:
        s = np.asarray(state, dtype=float)
        if s.shape != (5,) or not np.all(np.isfinite(s)):
            raise ValueError(f"reset state must be 5 finite numbers [X, Y, yaw, v, omega], got {state!r}")
        self._x = s.copy()
        self._rng = np.random.default_rng(self.seed)

    def residual(self, command: np.ndarray, v: float, omega: float) -> tuple[float, float]:
        """The network's (v, omega) residual for the current terrain."""
        out = self.net(np.array([[command[0], command[1], v, omega]]))[0]
        return float(out[2 * self._index]), float(out[2 * self._index + 1])

    def step(self, command: np.ndarray, duration: float) -> np.ndarray:
        cmd = np.asarray(command, dtype=float)
        if cmd.shape != (2,) or not np.all(np.isfinite(cmd)):
            raise ValueError(f"command must be 2 finite numbers [v_ref, omega_ref], got {command!r}")
        n = int(round(duration / self.dt))
        if n < 1 or abs(n * self.dt - duration) > 1e-6:
            raise ValueError(f"duration {duration} s is not a positive multiple of the network's step {self.dt} s")
        for _ in range(n):
            res_v, res_w = self.residual(cmd, self._x[3], self._x[4])
            self._x = nominal_step_with_pose(self.theta, self._x, cmd[0], cmd[1], res_v, res_w, self.dt, POSE_SUBSTEPS)
        self._x[2] = _wrap(self._x[2])
        return self._x.copy()

    def state(self) -> np.ndarray:
        """True `[X, Y, yaw, v, omega]`."""
        return self._x.copy()

    def measure(self) -> np.ndarray:
        s = self._x.copy()
        if self.noise_std is not None:
            s = s + self._rng.normal(0.0, 1.0, 5) * self.noise_std
            s[2] = _wrap(s[2])
        return s
