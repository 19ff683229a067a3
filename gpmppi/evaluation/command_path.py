"""The stack's command path between planner cycles, in simulated time: a command reaches egress after its latency,
egress (`SafetyCycle`) sends on acceptance, at its steady rate and at the watchdog's deadline, the plant holds each
output until the next (taken at the base's first tick after its arrival when the base has ticks: the terrain
cycle's `base_period_s`), and the terrain service's cycle (`TerrainCycle`) gets states and the commands of its
`command_source` and solves when it would in the stack; its weights go to the planner cycle at that time.

Times are the simulation's [s]; stamps are its nanoseconds (states are stamped when measured, and egress's and the
planner's clocks are the simulation's, so a command's age at egress is its latency).
"""

from __future__ import annotations

from collections import deque
from typing import Protocol

import numpy as np

from gpmppi.mppi.cycle import PlannerCycle
from gpmppi.safety import SafetyConfig, SafetyCycle
from gpmppi.terrain.cycle import TerrainCycle, TerrainCycleConfig
from gpmppi.terrain.estimate import EstimatorLike

_EPS = 1e-9


class SteppablePlant(Protocol):
    def step(self, command: np.ndarray, duration: float) -> np.ndarray: ...


def _ns(t: float) -> int:
    return round(t * 1e9)


class CommandPath:
    """Planner command -> egress -> base (plant), and states + commands -> terrain cycle -> weights."""

    def __init__(
        self, safety: SafetyConfig | None, terrain: TerrainCycleConfig, n_terrains: int,
        estimator: EstimatorLike | None,
    ) -> None:
        self.egress = SafetyCycle(safety) if safety is not None else None
        self.source = terrain.command_source
        self.terrain = TerrainCycle(terrain, n_terrains, estimator, record_pairs=True) if estimator is not None \
            else None
        self.pending: deque[tuple[float, int, np.ndarray]] = deque()  # (arrival at egress [s], stamp, command)
        # the base takes an output at its first tick at or after the arrival, when `terrain.base_period_s` says it
        # has ticks (the sim's 100 Hz steps, in phase with the states); until then it holds the previous one
        self.base_period = terrain.base_period_s
        self.taking: deque[tuple[float, np.ndarray]] = deque()  # (when the base takes it [s], command)
        self.state_time = 0.0  # the newest state's time: the base's ticks are in phase with it
        self.active = np.zeros(2)  # what the base applies now
        self.weights_ok = False  # whether the last solve succeeded (the weights the planner has now)
        # whether the last solve's weights name a top ground (TerrainEstimate.identified); before one, the
        # estimator's starting weights (an estimator that names no top on its uniform start says so)
        self.identified = bool(getattr(estimator, "identified", True))
        self.base_times: list[float] = []
        self.base_commands: list[np.ndarray] = []
        self.base_reasons: list[str] = []
        self.refusals: list[str] = []
        self.solves: list[tuple[float, int, np.ndarray, bool]] = []  # (time, stamp, weights, ok) of each solve
        self.unknown: list[tuple[float, float, bool]] = []  # (time, P(unknown), unknown_active) of each solve

    # ---- inputs at a planner cycle
    def on_state(self, stamp_ns: int, state: np.ndarray, now: float) -> None:
        self.state_time = now
        if self.terrain is not None:
            self.terrain.on_states([(stamp_ns, state)], now)

    def on_planned(self, now: float, arrival: float, stamp_ns: int, command: np.ndarray) -> None:
        """The planner published `command` (for the state stamped `stamp_ns`) at `now`; egress gets it at `arrival`."""
        if self.terrain is not None and self.source == "cmd":
            self.terrain.on_command(stamp_ns, command)
        self.pending.append((arrival, stamp_ns, np.asarray(command, dtype=np.float64).copy()))

    # ---- between planner cycles
    def _base(self, now: float, command: np.ndarray, reason: str, stamp_ns: int | None) -> None:
        u = np.asarray(command, dtype=np.float64).copy()
        if self.base_period is None:
            self.active = u
        else:
            ticks = np.ceil((now - self.state_time) / self.base_period - 1e-9)
            self.taking.append((self.state_time + ticks * self.base_period, u))
        self.base_times.append(now)
        self.base_commands.append(u.copy())
        self.base_reasons.append(reason)
        # egress's first output after a command keeps the command's stamp; repeats carry egress's clock, which
        # no state stamp matches, so they pair with nothing
        if self.terrain is not None and self.source == "base_cmd":
            self.terrain.on_output(_ns(now), u)
            if stamp_ns is not None:
                self.terrain.on_command(stamp_ns, u)

    def _take(self, now: float) -> None:
        while self.taking and self.taking[0][0] <= now + _EPS:
            self.active = self.taking.popleft()[1]

    def _events(self, now: float, planner: PlannerCycle) -> None:
        self._take(now)
        while self.pending and self.pending[0][0] <= now + _EPS:
            _, stamp, u = self.pending.popleft()
            if self.egress is None:
                self._base(now, u, "planner", stamp)
                continue
            refusal = self.egress.on_command(float(u[0]), float(u[1]), stamp, now, _ns(now))
            if refusal is not None:
                self.refusals.append(refusal)
        if self.egress is not None and (sent := self.egress.step(now)) is not None:
            out = sent.output
            self._base(now, np.array([out.v, out.omega]), out.reason, sent.command_stamp_ns)
        self._take(now)
        if self.terrain is not None and self.terrain.pending and self.terrain.wait_s(now) <= _EPS:
            update = self.terrain.solve()
            self.weights_ok = update.ok
            self.identified = update.identified
            self.solves.append((now, update.stamp_ns, update.weights.copy(), update.ok))
            self.unknown.append((now, update.unknown, update.unknown_active))
            planner.on_weights(update.weights, now, unknown_active=update.unknown_active,
                               unknown_channel=update.unknown_channel)

    def _next(self, now: float, end: float) -> float:
        t = end
        if self.pending:
            t = min(t, self.pending[0][0])
        if self.taking:
            t = min(t, self.taking[0][0])
        if self.egress is not None:
            t = min(t, self.egress.next_due(now))
        if self.terrain is not None and self.terrain.pending:
            t = min(t, now + self.terrain.wait_s(now))
        return max(t, now + 1e-7) if t < end else end

    def advance(self, plant: SteppablePlant, start: float, end: float, planner: PlannerCycle) -> np.ndarray:
        """Run the path's events in [start, end) and the plant between them; the plant's state at `end`.

        A plant with a `command_period_s` (the residual network's 0.1 s step) takes a command only at the start of
        each such period, as a base that samples its input at its own control rate: the path's events inside a
        period happen at their times, and the plant holds the command that was active when the period began."""
        now = start
        state = None
        period = getattr(plant, "command_period_s", None)
        while now < end - _EPS:
            self._events(now, planner)
            if period is None:
                nxt = self._next(now, end)
                state = plant.step(self.active, nxt - now)
                now = nxt
                continue
            held = self.active.copy()
            period_end = min(now + period, end)
            t = self._next(now, period_end)
            while t < period_end - _EPS:
                self._events(t, planner)
                t = self._next(t, period_end)
            state = plant.step(held, period_end - now)
            now = period_end
        if state is None:
            raise ValueError(f"empty planner cycle [{start}, {end})")
        return np.asarray(state, dtype=np.float64).copy()
