"""Fitting what the terrain estimator takes from offline drives: the per-terrain command-change gains
(`command_change: per_terrain`, gpmppi/data/terrain_command_gains.yaml) and each terrain's velocity response
(`response: steady_map`, gpmppi/data/terrain_response.yaml; gpmppi.profile.response).

Pure but for the plant: every function gets a `plant_for(terrain)` that builds a fresh plant on that terrain (the
physics plant, or the paper's residual net), so the caller decides which plant and seed; `gpmppi evaluate
terrain-gains` and `terrain-response` are the CLI over them. On a robot the same drives give the same fits: the
excitation commands for the gains and the rates, each command of the grid held until the velocities settle for the
steady map.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import yaml

from gpmppi.gp.model_file import GPModel
from gpmppi.plant.excitation import drive
from gpmppi.plant.physics import PhysicsPlant
from gpmppi.profile.response import TerrainResponse
from gpmppi.terrain.separability import transitions

# the grid of held commands of the shipped response: v_ref [m/s], omega_ref [rad/s] (no -0.0; covers the planner's +-pi)
RESPONSE_V_REF = np.round(np.arange(0.0, 2.0 + 1e-9, 0.2), 4)
RESPONSE_OMEGA_REF = np.round(np.arange(-3.2, 3.2 + 1e-9, 0.2), 4) + 0.0

PlantFor = Callable[[str], PhysicsPlant]  # terrain -> a fresh plant on it (anything with PhysicsPlant's interface)


def fit_command_gain(model: GPModel, states: np.ndarray, commands: np.ndarray, terrain: str) -> np.ndarray:
    """(2,) least-squares gain of `terrain`'s GP residual on the change of command since the previous step.

    `states` (T+1, 5) measured, `commands` (T, 2) applied between them, all on `terrain`: the gain per output of
    `y - m_terrain` on `du_k = u_k - u_{k-1}` (the first step's du is 0).
    """
    u = np.asarray(commands, dtype=np.float64)
    tr = transitions(model, states, u, [terrain] * u.shape[0])
    e = tr.y - tr.mean[:, list(model.terrains).index(terrain)]
    du = np.diff(u, axis=0, prepend=u[:1])
    return np.sum(du * e, axis=0) / np.maximum(np.sum(du * du, axis=0), 1e-12)


def fit_command_gains(
    model: GPModel, plant_for: PlantFor, distance: float, seed: int, dt: float = 0.1
) -> dict[str, np.ndarray]:
    """Per terrain of `model`, the command-change gain (`fit_command_gain`) on `distance` m of excitation drive of
    the plant on it (the training data's excitation commands, not a controller), in the model's terrain order."""
    gains = {}
    for terrain in model.terrains:
        run = drive(plant_for(terrain), terrain, distance, seed=seed, dt=dt)
        # command[k] is applied over [t_k, t_k+1): the last one has no next state
        gains[terrain] = fit_command_gain(model, run.state, run.command[:-1], terrain)
    return gains


def command_gains_yaml(gains: dict[str, np.ndarray], written_by: str) -> str:
    """The gains file (`gpmppi.terrain.settings.load_command_gains` reads it back), gains rounded to 4 decimals."""
    body = {"version": 1, "gains": {t: [round(float(x), 4) for x in g] for t, g in gains.items()}}
    return ("# Per-terrain command-change gains of the terrain estimator (gpmppi/terrain/estimator.py, "
            "command_change:\n"
            "# per_terrain): the GP residual per unit change of command since the previous step, [v, omega].\n"
            f"# Written by: {written_by}\n" + yaml.safe_dump(body, sort_keys=False))


def fit_rate(steady_at, states: np.ndarray, commands: np.ndarray) -> np.ndarray:
    """(2,) least-squares one-step rate of `v_{k+1} - v_k = rate (S(u_k) - v_k)` per output on one terrain's drive.

    `steady_at(u) -> (2,)` is that terrain's steady map; `states` (T+1, 5) measured, `commands` (T, 2) applied between
    them. Clipped to (0, 1].
    """
    x = np.asarray(states, dtype=np.float64)[:, 3:5]
    u = np.asarray(commands, dtype=np.float64)
    if x.shape[0] != u.shape[0] + 1:
        raise ValueError(f"need states (T+1, 5) and commands (T, 2); got {np.shape(states)}, {np.shape(commands)}")
    gap = np.array([steady_at(c) for c in u]) - x[:-1]
    rate = np.sum((x[1:] - x[:-1]) * gap, axis=0) / np.maximum(np.sum(gap * gap, axis=0), 1e-12)
    return np.clip(rate, 1e-3, 1.0)


def steady_map(
    plant: PhysicsPlant, v_ref: np.ndarray, omega_ref: np.ndarray, settle: float, average: float, dt: float = 0.1
) -> np.ndarray:
    """(A, B, 2) the steady (v, omega) under each held command of the grid: each held from rest for `settle` s, its
    measured (sensor-noisy) velocities averaged over the next `average` s."""
    steady = np.zeros((len(v_ref), len(omega_ref), 2))
    for i, v in enumerate(v_ref):
        for j, w in enumerate(omega_ref):
            plant.reset(np.zeros(5))
            u = np.array([v, w])
            for _ in range(int(round(settle / dt))):
                plant.step(u, dt)
            seen = []
            for _ in range(max(1, int(round(average / dt)))):
                plant.step(u, dt)
                seen.append(plant.measure()[3:5])
            steady[i, j] = np.mean(seen, axis=0)
    return steady


def fit_response(
    terrains: Sequence[str], plant_for: PlantFor, settle: float, average: float, distance: float, seed: int,
    v_ref: np.ndarray = RESPONSE_V_REF, omega_ref: np.ndarray = RESPONSE_OMEGA_REF, dt: float = 0.1,
) -> TerrainResponse:
    """Each terrain's response: its `steady_map` on a fresh plant, then the one-step rate of approach to it
    (`fit_rate`) on `distance` m of excitation drive of another fresh plant."""
    names = list(terrains)
    steady = np.zeros((len(names), len(v_ref), len(omega_ref), 2))
    rates = np.zeros((len(names), 2))
    for m, terrain in enumerate(names):
        steady[m] = steady_map(plant_for(terrain), v_ref, omega_ref, settle, average, dt)
        one = TerrainResponse(v_ref, omega_ref, (terrain,), steady[m:m + 1], np.ones((1, 2)))
        run = drive(plant_for(terrain), terrain, distance, seed=seed, dt=dt)
        # command[k] is applied over [t_k, t_k+1): the last one has no next state
        rates[m] = fit_rate(lambda c, one=one: one.steady_at(c)[0], run.state, run.command[:-1])
    return TerrainResponse(v_ref, omega_ref, tuple(names), steady, rates)


def response_yaml(response: TerrainResponse, written_by: str) -> str:
    """The response file (`gpmppi.profile.response.load_response` reads it back)."""
    return response.to_yaml(
        "# Each terrain's velocity response to a held command (gpmppi/profile/response.py): the steady (v, omega)\n"
        "# on a (v_ref, omega_ref) grid and the one-step rate of approach to it. Used by the terrain estimator.\n"
        f"# Written by: {written_by}\n")
