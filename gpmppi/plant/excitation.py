"""Excitation commands and in-memory datasets: drive a plant over terrains and return arrays.

The excitation mixes segment kinds so the data cover the whole command box
(v in [0, v_max], omega in [-w_max, w_max]), the coupled region the planner uses (fast forward
driving with moderate turning), and the jumpy commands MPPI produces:

- hold:   a random command held 0.5-4 s (uniform over the box, or from the planner's region);
- ramp:   a linear ramp from the current command to a random one over 1-4 s;
- chirp:  a forward speed with a sinusoidal yaw-rate command swept 0.1 -> 1.5 Hz over 4-10 s;
- jitter: a random walk of the command, changing every tick, 2-6 s (MPPI-like).

Optionally (`lane_holds`, off by default so the default stream is unchanged) a share of the segments are long holds
where the planner drives (`LANE_V` x `LANE_OMEGA`): the terrain estimator's steady map must be right to about
1 mrad/s there, and the holds at random commands leave 2-6 (docs/terrain_identification.md, "Calibration from logs").
Optionally too (`top_holds`, off by default) straight holds near the robot's top speed are added between the segments
(`TOP_HOLD_SHARES` of `top_speed`, held `TOP_HOLD_S`): the GP's one-step error where the lanes drive steadily near
the top speed is what the terrain filter and the novelty test read there (gpmppi/terrain/steady_bias.py). They are
drawn from a random stream of their own and leave the command the next segment starts from as it was, so the other
segments are the plain stream's, and `drive` counts the distance of those alone.

Array form of a run (agreed with the trainer): per tick k at t_k = k dt, `state[k]` is the measured
`[X, Y, yaw, v, omega]` at t_k and `command[k]` the `[v_ref, omega_ref]` applied over [t_k, t_k + dt).
One run is one contiguous segment (so a residual pairs tick k with tick k+1 of the same run).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from gpmppi.plant.physics import PhysicsPlant
from gpmppi.plant.terrains import TerrainSet

SEGMENT_KINDS = ("hold", "ramp", "chirp", "jitter")
SEGMENT_PROBS = (0.35, 0.2, 0.15, 0.3)
LANE_V = (0.8, 1.8)  # forward-speed commands of the planner's lanes [m/s]
LANE_OMEGA = 0.8  # ... and their largest |yaw-rate command| [rad/s]
LANE_HOLD_S = (5.0, 8.0)  # (shortest, longest) lane hold [s]: settled, then averaged for 3.4-6.4 s
TOP_HOLD_SHARES = (0.7, 1.0)  # a top hold's v command, as shares of the top speed (omega_ref 0)
TOP_HOLD_S = (5.0, 8.0)  # (shortest, longest) top hold [s]: the motors settle in 1-3 s


class Excitation:
    """Seeded stream of excitation command segments, each an (n, 2) array of per-tick commands."""

    def __init__(
        self, seed: int = 0, dt: float = 0.1, v_max: float = 2.0, w_max: float = np.pi,
        hold_s: tuple[float, float] = (0.5, 4.0), lane_holds: float = 0.0, top_holds: float = 0.0,
        top_speed: float | None = None,
    ) -> None:
        if not 0.0 <= lane_holds < 1.0:
            raise ValueError(f"lane_holds {lane_holds}: the share of lane holds must be in [0, 1)")
        if not 0.0 <= top_holds <= 1.0:
            raise ValueError(f"top_holds {top_holds}: the chance of a top hold after a segment must be in [0, 1]")
        self.rng = np.random.default_rng(seed)
        self.dt = dt
        self.v_max = v_max
        self.w_max = w_max
        self.hold_s = hold_s  # (shortest, longest) held command [s]
        self.lane_holds = lane_holds  # share of the segments that are lane holds (LANE_V, LANE_OMEGA, LANE_HOLD_S)
        self.current = np.zeros(2)
        self.top_holds = top_holds  # chance of a top hold added after each segment (TOP_HOLD_SHARES, TOP_HOLD_S)
        self.top_speed = float(top_speed) if top_speed is not None else v_max  # the robot's top speed [m/s]
        # a stream of their own: the other segments' draws are the plain stream's whatever top_holds is
        self._top_rng = np.random.default_rng([seed, 1]) if top_holds > 0.0 else None
        self.extra = False  # whether the last segment handed out was an added top hold

    def _random_command(self) -> np.ndarray:
        if self.rng.random() < 0.5:  # uniform over the box
            return np.array([self.rng.uniform(0.0, self.v_max), self.rng.uniform(-self.w_max, self.w_max)])
        # the planner's region: fast forward, moderate turning
        v = self.rng.uniform(min(0.8, self.v_max), self.v_max)
        w = float(np.clip(self.rng.normal(0.0, 0.7), -self.w_max, self.w_max))
        return np.array([v, w])

    def _ticks(self, lo: float, hi: float) -> int:
        return max(1, int(round(self.rng.uniform(lo, hi) / self.dt)))

    def lane_hold(self) -> np.ndarray:
        """A lane hold: v_ref in LANE_V, omega_ref within LANE_OMEGA (both within the caps), held LANE_HOLD_S."""
        v = self.rng.uniform(min(LANE_V[0], self.v_max), min(LANE_V[1], self.v_max))
        w = self.rng.uniform(-min(LANE_OMEGA, self.w_max), min(LANE_OMEGA, self.w_max))
        seg = np.tile([v, w], (self._ticks(*LANE_HOLD_S), 1))
        self.current = seg[-1].copy()
        return seg

    def lane_hold_next(self) -> bool:
        """Whether the next segment is a lane hold (a share `lane_holds` of them)."""
        # no draw at all when off: the default stream (and the shipped GP's data) stays as it was
        return self.lane_holds > 0.0 and bool(self.rng.random() < self.lane_holds)

    def top_hold(self) -> np.ndarray:
        """A straight hold near the top speed (TOP_HOLD_SHARES of `top_speed`, within v_max) for TOP_HOLD_S, from
        the top holds' own stream. `current` is left as it was: the next segment starts from the command before."""
        assert self._top_rng is not None
        lo, hi = (min(s * self.top_speed, self.v_max) for s in TOP_HOLD_SHARES)
        v = self._top_rng.uniform(lo, hi)
        n = max(1, int(round(self._top_rng.uniform(*TOP_HOLD_S) / self.dt)))
        return np.tile([v, 0.0], (n, 1))

    def next_segment(self) -> np.ndarray:
        # a top hold after a plain segment, never two in a row
        if self._top_rng is not None and not self.extra and self._top_rng.random() < self.top_holds:
            self.extra = True
            return self.top_hold()
        self.extra = False
        return self.lane_hold() if self.lane_hold_next() else self.random_segment()

    def random_segment(self) -> np.ndarray:
        """A hold, ramp, chirp or jitter segment (module docstring), from the current command."""
        kind = SEGMENT_KINDS[self.rng.choice(len(SEGMENT_KINDS), p=SEGMENT_PROBS)]
        if kind == "hold":
            seg = np.tile(self._random_command(), (self._ticks(*self.hold_s), 1))
        elif kind == "ramp":
            n = self._ticks(1.0, 4.0)
            frac = (np.arange(1, n + 1) / n)[:, None]
            seg = self.current + frac * (self._random_command() - self.current)
        elif kind == "chirp":
            n = self._ticks(4.0, 10.0)
            t = np.arange(n) * self.dt
            f0, f1, duration = 0.1, 1.5, n * self.dt
            phase = 2 * np.pi * (f0 * t + 0.5 * (f1 - f0) / duration * t**2)
            amp = self.rng.uniform(0.3, self.w_max)
            seg = np.column_stack([np.full(n, self.rng.uniform(0.0, self.v_max)), amp * np.sin(phase)])
        else:
            n = self._ticks(2.0, 6.0)
            steps = self.rng.normal(0.0, 1.0, (n, 2)) * np.array([0.15, 0.35])
            seg = np.empty((n, 2))
            c = self.current.copy()
            for k in range(n):
                c = c + steps[k]
                c[0] = np.clip(c[0], 0.0, self.v_max)
                c[1] = np.clip(c[1], -self.w_max, self.w_max)
                seg[k] = c
        seg[:, 0] = np.clip(seg[:, 0], 0.0, self.v_max)
        seg[:, 1] = np.clip(seg[:, 1], -self.w_max, self.w_max)
        self.current = seg[-1].copy()
        return seg


@dataclass
class TerrainRun:
    """One contiguous drive on one terrain, sampled every `dt` (see the module docstring)."""

    terrain: str
    dt: float
    time: np.ndarray  # (n,) seconds since the start of the run
    state: np.ndarray  # (n, 5) measured [X, Y, yaw, v, omega] at t_k
    command: np.ndarray  # (n, 2) [v_ref, omega_ref] applied over [t_k, t_k + dt)
    true_state: np.ndarray  # (n, 5) noise-free state at t_k

    @property
    def distance(self) -> float:
        return float(np.sum(np.hypot(*np.diff(self.true_state[:, :2], axis=0).T)))


def drive(
    plant: PhysicsPlant,
    terrain: str,
    distance: float,
    seed: int = 0,
    dt: float = 0.1,
    max_time: float | None = None,
    progress: Callable[[float], None] | None = None,
    lane_holds: float = 0.0,
    top_holds: float = 0.0,
) -> TerrainRun:
    """Drive `plant` on `terrain` with excitation commands (`lane_holds`, `top_holds`: `Excitation`'s, the top speed
    the plant's `max_speed`) until the plain segments have covered `distance` metres (the added top holds' metres
    come on top)."""
    if not distance > 0:
        raise ValueError(f"distance must be positive, got {distance}")
    limit = max_time if max_time is not None else 20.0 * distance + 600.0
    plant.set_terrain(terrain)
    plant.reset(np.zeros(5))
    # the top speed is only read when top holds are asked for: other plants (the residual net) have no `robot`
    exc = Excitation(seed=seed, dt=dt, lane_holds=lane_holds, top_holds=top_holds,
                     top_speed=float(plant.robot.max_speed) if top_holds > 0.0 else None)
    states, trues, cmds = [], [], []
    travelled = 0.0
    true = plant.state()
    while travelled < distance:
        if len(cmds) * dt > limit:
            raise RuntimeError(f"terrain {terrain!r}: {travelled:.0f} m after {limit:.0f} s; the robot is stuck")
        for cmd in exc.next_segment():
            states.append(plant.measure())
            trues.append(true)
            cmds.append(cmd)
            nxt = plant.step(cmd, dt)
            if not exc.extra:
                travelled += float(np.hypot(nxt[0] - true[0], nxt[1] - true[1]))
            true = nxt
            if progress is not None:
                progress(min(travelled, distance))
            if travelled >= distance:
                break
    n = len(cmds)
    return TerrainRun(terrain, dt, np.arange(n) * dt, np.array(states), np.array(cmds), np.array(trues))


def simulate_dataset(
    terrains: TerrainSet,
    names: list[str] | None = None,
    distance: float = 2000.0,
    seed: int = 0,
    dt: float = 0.1,
    noise: bool = True,
    progress: Callable[[str, float], None] | None = None,
    lane_holds: float = 0.0,
    top_holds: float = 0.0,
) -> dict[str, TerrainRun]:
    """One run per terrain (default: every terrain but sand).

    Every terrain gets the same excitation command stream (seeded by `seed`; matched commands, as in
    the paper's data, so terrain differences are not confounded with different inputs) and its own
    sensor-noise seed. `lane_holds`: `Excitation`'s share of long holds where the planner drives (0: none);
    `top_holds`: its chance of a straight hold near the top speed added after a segment (0: none).
    """
    names = names if names is not None else [n for n in terrains.names if n != "sand"]
    runs: dict[str, TerrainRun] = {}
    for i, name in enumerate(names):
        terrains.get(name)
        plant = PhysicsPlant(terrains, name, seed=seed * 1000 + i, noise=noise)
        cb = (lambda d, _n=name: progress(_n, d)) if progress is not None else None
        runs[name] = drive(plant, name, distance, seed=seed, dt=dt, progress=cb, lane_holds=lane_holds,
                           top_holds=top_holds)
    return runs


def runs_to_series(runs: dict[str, TerrainRun] | dict[str, list[TerrainRun]]) -> dict[str, dict[str, np.ndarray]]:
    """The trainer's series form: terrain -> {"v", "w", "v_ref", "w_ref", "seg"} (one segment per run)."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for name, value in runs.items():
        parts = value if isinstance(value, list) else [value]
        out[name] = {
            "v": np.concatenate([r.state[:, 3] for r in parts]),
            "w": np.concatenate([r.state[:, 4] for r in parts]),
            "v_ref": np.concatenate([r.command[:, 0] for r in parts]),
            "w_ref": np.concatenate([r.command[:, 1] for r in parts]),
            "seg": np.concatenate([np.full(len(r.command), i) for i, r in enumerate(parts)]),
        }
    return out
