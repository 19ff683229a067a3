"""Each ground's GP one-step error in steady straight driving near the top speed (issues 41 and 44).

On a straight at a held speed the motors' integral action brings every ground to (nearly) the same speed, so the
one-step evidence the terrain filter and the novelty test read there is each ground's GP bias at that steady state:
`y - m_i(u, x)`, the measured one-step velocity residual (next velocity minus the nominal step) minus ground i's GP
mean. The command-change part is 0 on a held command. This module measures it directly: the plant driven from rest
on each ground under a held straight command, and the residual's mean over the settled tail under every ground's
GP, in the novelty test's spreads (the spread of a 2 s windowed mean on known ground: a bias of `enter` = 3.5 of them
reads as unknown ground by itself). The true ground's own bias is what a fix of the GP must shrink; the gaps
between the grounds' biases are what the filter can tell them apart by there.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gpmppi.gp.exact import ExactPredictor
from gpmppi.gp.model_file import GPModel
from gpmppi.models.dynamic_unicycle import velocity_step_exact
from gpmppi.plant.physics import PhysicsPlant
from gpmppi.plant.terrains import TerrainSet
from gpmppi.terrain.novelty import profile_novelty

TOP_SPEED_SHARES = (0.7, 0.8, 0.9, 0.95, 1.0)  # the held v commands, as shares of the robot's top speed
HOLD_S = 10.0  # each command held from rest [s] (the motors settle in ~1-2 s; the 45 kg robot's in ~3)
SETTLE_S = 4.0  # the tail after this is averaged [s]


@dataclass(frozen=True)
class SteadyBias:
    """The settled one-step residual of each ground's GP on each driven ground, per held straight command."""

    terrains: tuple[str, ...]  # the model's grounds: both the driven ones and the GPs, in this order
    v_ref: np.ndarray  # (K,) the held v commands [m/s]
    mean: np.ndarray  # (K, M driven, M GP, 2) mean of y - m_i over the settled tail [m/s, rad/s]
    speed: np.ndarray  # (K, M driven) the mean measured speed over the tail [m/s]
    spread: tuple[float, float]  # the novelty test's spread of the windowed mean (v, omega)

    @property
    def in_spreads(self) -> np.ndarray:
        """(K, M, M, 2) `mean` in units of the novelty test's spread."""
        return self.mean / np.asarray(self.spread)[None, None, None, :]

    @property
    def own(self) -> np.ndarray:
        """(K, M, 2) the true ground's own GP bias in spreads (driven ground j under GP j)."""
        m = len(self.terrains)
        return self.in_spreads[:, np.arange(m), np.arange(m)]

    def worst_own(self) -> float:
        """The largest |own bias| in spreads, over commands, grounds and both channels."""
        return float(np.max(np.abs(self.own)))

    def rows(self) -> list[dict]:
        """One JSON-ready row per command and driven ground: speed, and every GP's bias in spreads (v, omega)."""
        out = []
        for k, v in enumerate(self.v_ref):
            for j, driven in enumerate(self.terrains):
                out.append({"v_ref": round(float(v), 4), "driven": driven, "speed": round(float(self.speed[k, j]), 4),
                            "bias_spreads": {t: [round(float(b), 2) for b in self.in_spreads[k, j, i]]
                                             for i, t in enumerate(self.terrains)}})
        return out


def top_speed_commands(terrains: TerrainSet, shares: Sequence[float] = TOP_SPEED_SHARES) -> np.ndarray:
    """The held v commands: `shares` of the robot's top speed (its wheel-speed limit, `max_speed`) [m/s]."""
    return np.asarray(shares, dtype=np.float64) * float(terrains.robot.max_speed)


def steady_bias(
    model: GPModel, terrains: TerrainSet, v_ref: Sequence[float] | np.ndarray, hold_s: float = HOLD_S,
    settle_s: float = SETTLE_S, noise: bool = False, seed: int = 0, omega_ref: float = 0.0,
) -> SteadyBias:
    """Drive the physics plant from rest on each of `model`'s grounds under each held command (`v_ref`, `omega_ref`:
    straight by default) for `hold_s`, and average every ground's GP one-step residual error over the steps after
    `settle_s` (module docstring). `noise`: the plant's sensor noise on the states the residuals are read from
    (seeded)."""
    names = tuple(model.terrains)
    missing = [t for t in names if t not in terrains.names]
    if missing:
        raise ValueError(f"the plant's terrain set lacks the model's grounds {missing}")
    if not 0.0 <= settle_s < hold_s - model.dt:
        raise ValueError(f"settle_s {settle_s} must leave steps of the {hold_s} s hold to average")
    cmds = np.asarray(v_ref, dtype=np.float64).reshape(-1)
    m, dt = len(names), float(model.dt)
    n = int(round(hold_s / dt))
    first = int(round(settle_s / dt))
    predictor = ExactPredictor(model)
    mean = np.zeros((len(cmds), m, m, 2))
    speed = np.zeros((len(cmds), m))
    for k, v in enumerate(cmds):
        for j, ground in enumerate(names):
            plant = PhysicsPlant(terrains, ground, seed=seed * 1000 + j, noise=noise)
            plant.reset(np.zeros(5))
            states = [plant.measure()]
            for _ in range(n):
                plant.step(np.array([v, omega_ref]), dt)
                states.append(plant.measure())
            x = np.array(states[first:])  # the settled tail: x[i] -> x[i + 1] under the held command
            u = np.column_stack([np.full(len(x) - 1, v), np.full(len(x) - 1, omega_ref)])
            v_nom, w_nom = velocity_step_exact(model.theta, x[:-1, 3].copy(), x[:-1, 4].copy(), u[:, 0].copy(),
                                               u[:, 1].copy(), dt)
            y = np.column_stack([x[1:, 3] - v_nom, x[1:, 4] - w_nom])  # (T, 2)
            gp, _ = predictor.predict(np.column_stack([u, x[:-1, 3:5]]), with_var=False)  # (T, 2M)
            err = y[:, None, :] - gp.reshape(len(y), m, 2)
            mean[k, j] = err.mean(axis=0)
            speed[k, j] = float(x[:, 3].mean())
    spread = profile_novelty(model).spread
    return SteadyBias(names, cmds, mean, speed, (float(spread[0]), float(spread[1])))
