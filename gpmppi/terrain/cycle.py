"""The terrain service's cycle, free of any transport: states and the commands the base received in, terrain weights
out. The terrain service drives one from its Zenoh loop and the closed-loop evaluation from its simulation, so both
pair, gate, estimate and clean up the same way:

- pairing: a command carries the stamp of the state it was planned from (egress keeps it on the first output after
  accepting it), so the command applied over the transition from the state stamped t_k is the one stamped t_k:
  pairing by stamp, not by arrival order, stays right when the loop runs late and the next command is already in;
- gating: a transition whose stamp gap differs from `dt` by more than `dt_tolerance * dt` (a lost or late state)
  is not observed;
- timing: it solves once the command for the newest state has arrived (the planner is done with that state, so the
  solve stays off the cores the control path needs), or `command_wait_s` after the state arrived;
- clean-up: commands older than the newest state are dropped (no later transition can use them); the weights are
  clipped to [0, 1] and renormalised, a non-finite residual reads 0;
- `pairing: applied` (the default with `command_source: base_cmd`): a transition is observed with the command the
  base actually held over it, the time average of egress's outputs by their arrival (`on_output`), not the command
  planned from its first state. In the stack a state's command reaches the base a latency after the state (planning,
  two Zenoh hops): for that part of the step the base still runs the previous command, which the estimator's
  per-terrain command-change gains (fitted on drives whose commands change at the step boundaries) read as a terrain
  that responds more slowly (docs/deployed_path.md). A base that takes commands at its own ticks (the sim's 100 Hz
  plant steps, `base_period_s`) takes each output from its first tick after the arrival.

Times: `now` is a monotonic time [s]; stamps are integer nanoseconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, Field, model_validator

from gpmppi.terrain.estimate import EstimatorLike

CommandSource = Literal["base_cmd", "cmd"]
Pairing = Literal["stamp", "applied"]


class TerrainCycleConfig(BaseModel):
    """The terrain service's pairing and timing (its settings inherit these fields)."""

    dt: float = Field(0.1, gt=0, le=1.0, description="expected time between states (the GP model's step) [s]")
    dt_tolerance: float = Field(
        0.5, gt=0, lt=1.0, description="skip pairs whose spacing differs from dt by more (fraction of dt, below 1: "
        "a pair of states with no time between them is never a step)"
    )
    command_source: CommandSource = Field(
        "base_cmd", description="'base_cmd' (what the base got, egress's output) or 'cmd' (the planner's output)"
    )
    command_wait_s: float = Field(
        0.05, ge=0, le=1.0, description="solve once the command for the newest state has arrived, or after this "
        "long [s]"
    )
    pairing: Pairing | None = Field(
        None, description="'stamp': a transition with the command planned from its first state; 'applied' (needs "
        "command_source base_cmd): with the time average of the base's outputs over it, by their arrival; None: "
        "'applied' with base_cmd, 'stamp' with cmd"
    )

    base_period_s: float | None = Field(
        None, gt=0, le=0.1, description="pairing 'applied': the base takes a command at its own ticks, this far apart "
        "and in phase with the states (the sim: 1 / step_hz, 0.01 s), so an output counts from the first tick after "
        "it arrived [s] (None: from its arrival)"
    )

    @model_validator(mode="after")
    def _applied_needs_base(self) -> TerrainCycleConfig:
        if self.pairing == "applied" and self.command_source != "base_cmd":
            raise ValueError("pairing 'applied' averages what the base received: it needs command_source 'base_cmd' "
                             f"(got {self.command_source!r})")
        return self

    @property
    def effective_pairing(self) -> Pairing:
        if self.pairing is not None:
            return self.pairing
        return "applied" if self.command_source == "base_cmd" else "stamp"

    @classmethod
    def from_settings(cls, settings: BaseModel | dict) -> TerrainCycleConfig:
        """The cycle's fields of the terrain service's settings (an object or a service entry's `config` dict)."""
        values = settings if isinstance(settings, dict) else settings.model_dump()
        return cls.model_validate({k: v for k, v in values.items() if k in cls.model_fields})


@dataclass
class WeightsUpdate:
    """One set of weights to publish, stamped with the newest state it answers."""

    weights: np.ndarray  # (M,) in the model's terrain order, on the simplex
    ok: bool  # the estimator solved (False: the prior, a short history, a failed solve)
    residual: float
    stamp_ns: int
    error: str | None = None  # a failed solve past the warm-up (the service logs it as an error)
    observed: int = 0  # transitions this update observed
    skipped: int = 0  # transitions skipped: no command for the state, or a gap off dt
    unknown: float = 0.0  # P(the ground is none of the trained ones), in [0, 1] (0: not assessed)
    unknown_active: bool = False  # the hysteretic decision on `unknown` (gpmppi.terrain.novelty.UnknownLatch)
    unknown_channel: str = ""  # which of the test's channels gave `unknown` (TerrainEstimate.unknown_channel)
    identified: bool = True  # whether the weights name a top ground (TerrainEstimate.identified)


class TerrainCycle:
    """Feed it commands (`on_command`) and states (`on_states`); when `wait_s(now)` is 0, `solve()`."""

    def __init__(
        self, config: TerrainCycleConfig, n_terrains: int, estimator: EstimatorLike | None = None,
        record_pairs: bool = False,
    ) -> None:
        self.config = config
        self.n_terrains = n_terrains
        self.estimator = estimator
        self.commands: dict[int, np.ndarray] = {}
        self.previous: tuple[int, np.ndarray] | None = None  # the newest state observed: (stamp, array)
        self.pending: list[tuple[int, np.ndarray]] = []
        self.pending_since = 0.0
        self.outputs: list[tuple[int, np.ndarray]] = []  # (arrival [ns], command) of the base's outputs, in order
        self.counts: dict[str, int] = {}
        # with `record_pairs`: what each transition was paired with (stamp of its first state, command or None)
        self.pairs: list[tuple[int, np.ndarray | None]] | None = [] if record_pairs else None

    @property
    def prior(self) -> np.ndarray:
        return np.full(self.n_terrains, 1.0 / self.n_terrains)

    def on_command(self, stamp_ns: int, command: Sequence[float] | np.ndarray) -> None:
        """A command from `command_source`, stamped with the state it answers (later ones with that stamp win)."""
        self.commands[int(stamp_ns)] = np.asarray(command, dtype=np.float64).reshape(2).copy()

    def on_output(self, received_ns: int, command: Sequence[float] | np.ndarray) -> None:
        """One output the base received at `received_ns` (on the states' clock), held until the next: `pairing:
        applied` averages them over each transition. Out-of-order arrivals are put in order."""
        received_ns = int(received_ns)
        period = self.config.base_period_s
        anchor = self.pending[-1][0] if self.pending else (self.previous[0] if self.previous is not None else None)
        if period is not None and anchor is not None:
            # the base's ticks are in phase with the states it measures: the first tick at or after the arrival
            step = round(period * 1e9)
            received_ns = anchor + -(-(received_ns - anchor) // step) * step
        entry = (received_ns, np.asarray(command, dtype=np.float64).reshape(2).copy())
        if self.outputs and entry[0] < self.outputs[-1][0]:
            self.outputs.append(entry)
            self.outputs.sort(key=lambda e: e[0])
        else:
            self.outputs.append(entry)

    def applied(self, start_ns: int, end_ns: int) -> np.ndarray | None:
        """The time average over [start_ns, end_ns] of the outputs held by the base, or None when none was held at
        `start_ns` (nothing had arrived yet)."""
        times = [t for t, _ in self.outputs]
        i = int(np.searchsorted(times, start_ns, side="right")) - 1
        if i < 0 or end_ns <= start_ns:
            return None
        total = np.zeros(2)
        t = start_ns
        for j in range(i, len(self.outputs)):
            nxt = self.outputs[j + 1][0] if j + 1 < len(self.outputs) else end_ns
            seg_end = min(nxt, end_ns)
            if seg_end > t:
                total += self.outputs[j][1] * (seg_end - t)
                t = seg_end
            if nxt >= end_ns:
                break
        return total / (end_ns - start_ns)

    def on_states(self, states: Sequence[tuple[int, np.ndarray]], now: float) -> None:
        """New states (stamp [ns], 5-array), oldest first, arrived at `now`."""
        if not states:
            return
        if not self.pending:
            self.pending_since = now
        self.pending += [(int(s), np.asarray(x, dtype=np.float64).copy()) for s, x in states]

    def wait_s(self, now: float) -> float:
        """How long to wait before solving: 0 when the newest state's command is in or the wait is over; inf when
        no state is pending."""
        if not self.pending:
            return float("inf")
        if self.pending[-1][0] in self.commands:
            return 0.0
        return max(0.0, self.config.command_wait_s - (now - self.pending_since))

    def prior_update(self, identified: bool) -> WeightsUpdate:
        """The prior (uniform, not solved), stamped with the newest pending state: what the service publishes while
        it builds its estimator. `identified`: whether the estimator it builds names a top on its start
        (`EstimatorConfig.names_top_at_start`): a uniform prior is a tie, whose argmax (the profile's first ground) is
        no identification, and a change from it counted as one would be the start's tie again."""
        stamp = self.pending[-1][0] if self.pending else 0
        return WeightsUpdate(self.prior, False, 0.0, stamp, identified=identified)

    def solve(self) -> WeightsUpdate:
        """Observe the pending states' transitions with their commands, estimate, clean up."""
        if self.estimator is None:
            raise RuntimeError("TerrainCycle.solve: no estimator yet (publish prior_update() until there is one)")
        if not self.pending:
            raise RuntimeError("TerrainCycle.solve: no pending state (wait until wait_s(now) is finite and 0)")
        c = self.config
        observed = skipped = 0
        for stamp, x in self.pending:
            if self.previous is not None:
                gap = (stamp - self.previous[0]) / 1e9
                command = self.commands.get(self.previous[0])
                if c.effective_pairing == "applied" and command is not None:
                    command = self.applied(self.previous[0], stamp)
                if command is not None and abs(gap - c.dt) <= c.dt_tolerance * c.dt:
                    self.estimator.observe(self.previous[1], command, x)
                    if self.pairs is not None:
                        self.pairs.append((self.previous[0], command.copy()))
                    observed += 1
                else:
                    if self.pairs is not None:
                        self.pairs.append((self.previous[0], None))
                    skipped += 1
                    name = "no_command" if command is None else "gap_off_dt"
                    self.counts[name] = self.counts.get(name, 0) + 1
            self.previous = (stamp, x)
        assert self.previous is not None
        # keep only commands that a later transition can still use
        for old in [t for t in self.commands if t < self.previous[0]]:
            del self.commands[old]
        # and the outputs from the one the base held at the newest state on
        held = int(np.searchsorted([t for t, _ in self.outputs], self.previous[0], side="right")) - 1
        if held > 0:
            del self.outputs[:held]
        est = self.estimator.estimate()
        weights = np.clip(np.asarray(est.weights, dtype=np.float64), 0.0, 1.0)
        weights = weights / weights.sum() if weights.sum() > 0 else self.prior
        residual = max(0.0, float(est.residual)) if np.isfinite(est.residual) else 0.0
        # a short history is the normal warm-up, not a failure worth an error line
        error = None
        if not est.ok and len(self.estimator) >= self.estimator.min_history:
            error = f"weight solve: {est.message}"
        stamp = self.pending[-1][0]
        self.pending = []
        # an estimator without the novelty test (the paper's, another's) says nothing: known ground
        unknown = float(getattr(est, "unknown", 0.0))
        unknown = float(np.clip(unknown, 0.0, 1.0)) if np.isfinite(unknown) else 0.0
        return WeightsUpdate(weights, bool(est.ok), residual, stamp, error, observed, skipped, unknown,
                             bool(getattr(est, "unknown_active", False)),
                             str(getattr(est, "unknown_channel", "")), bool(getattr(est, "identified", True)))
