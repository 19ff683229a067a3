"""The registered critics and what derives from them: the cost vector's layout and the summed and split terms.

Critics are registered once, before the kernels' modules read the layout (`gpmppi.mppi.bundles` does on import);
`register` after that is an error. The cost vector the kernels read is, in order: the task switches (`base.W_*`),
each critic's weight (registration order), then each critic's parameters (registration order, then the order of its
`params`).

The kernels' sums are built here from the registered terms, each as one function that calls every term of a task
kind in turn (`_chain`, its source written out here): the summed cost adds the terms in registration order, the split
adds each to its own slot. numba resolves those calls when it compiles, so they are plain calls inlined into the
kernels (a tuple of functions would be called through pointers). CUDA gets the same functions built from the terms'
device twins (`build_sums(jit, twin)`).

Stateful critics (`base.StepState`) get their state chains here too (`build_states`): the drivers start the tuple of
every stateful critic's value before a rollout's first step and advance it after each; a stateful term is called
with its own value (`Step.state[slot]`). What the planner adds for critics of the step's variances under the exact
GP comes from `CriticLayout.noise_costs`. No driver and no planner code names a critic.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

from numba import njit

from gpmppi.kernel_flags import FASTMATH
from gpmppi.mppi.critics.base import LANE_TASK_KINDS, TASK_KINDS, W_GOAL_GEODESIC, Critic
from gpmppi.mppi.kernel_cache import key_cache_to_outside_critics

__all__ = [
    "ByKind", "CriticLayout", "States", "Sums", "build_by_kind", "build_states", "build_sums", "layout", "register",
]

_REGISTERED: list[Critic] = []
_LAYOUT: CriticLayout | None = None


def register(critic: Critic) -> None:
    """Add a critic (a critic module's `CRITIC`); before the layout is read, names unique."""
    if _LAYOUT is not None:
        raise RuntimeError(f"critic {critic.name!r} registered after the kernels' layout was read: register critics "
                           "before importing gpmppi.mppi.bundles (or anything that imports it)")
    if any(c.name == critic.name for c in _REGISTERED):
        raise ValueError(f"a critic named {critic.name!r} is already registered")
    unknown = sorted(set(critic.tasks) - set(TASK_KINDS))
    if unknown or not critic.tasks:
        raise ValueError(f"critic {critic.name!r}: task kinds {list(critic.tasks)}; each must be one of "
                         f"{list(TASK_KINDS)}, at least one")
    _REGISTERED.append(critic)


@dataclass(frozen=True)
class CriticLayout:
    """The registered critics and the cost vector's layout."""

    critics: tuple[Critic, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.critics)

    def weight_index(self, name: str) -> int:
        return W_GOAL_GEODESIC + 1 + self.names.index(name)

    def param_index(self, name: str, param: str) -> int:
        """The index of critic `name`'s parameter `param` in the cost vector."""
        i = W_GOAL_GEODESIC + 1 + len(self.critics)
        for c in self.critics:
            for p in c.params:
                if (c.name, p) == (name, param):
                    return i
                i += 1
        raise KeyError(f"critic {name!r} has no parameter {param!r}")

    def first_param(self, name: str) -> int:
        """Where critic `name`'s parameters start (one past the last slot when it has none)."""
        c = self.critics[self.names.index(name)]
        return self.param_index(name, next(iter(c.params))) if c.params else self.size

    @property
    def size(self) -> int:
        return W_GOAL_GEODESIC + 1 + len(self.critics) + sum(len(c.params) for c in self.critics)

    def terms(self, task: str, terminal: bool) -> tuple[tuple[int, int, int, Callable], ...]:
        """(weight index, first parameter index, state slot (-1: stateless), term) of the critics of a task kind, stage
        or terminal."""
        return tuple((self.weight_index(c.name), self.first_param(c.name), self.state_slot(c.name), c.term)
                     for c in self.critics if task in c.tasks and c.terminal == terminal)

    @property
    def stateful(self) -> tuple[Critic, ...]:
        """The critics that carry a value from step to step (`base.StepState`), in the order of the drivers' tuple."""
        return tuple(c for c in self.critics if c.state is not None)

    def state_slot(self, name: str) -> int:
        """Where critic `name`'s value is in the drivers' state tuple (`Step.state`); -1 for a stateless critic."""
        names = [c.name for c in self.stateful]
        return names.index(name) if name in names else -1

    def noise_costs(
        self, weights: Mapping[str, float], horizon: int, noise_v: float, noise_w: float
    ) -> dict[str, float]:
        """Each critic's cost of the likelihood noise the kernels leave out of the step's variances, by name: the
        critics that declare one (`Critic.noise_cost`), with their `weights`."""
        return {c.name: c.noise_cost(weights[c.name], horizon, noise_v, noise_w) for c in self.critics
                if c.noise_cost is not None}


def layout() -> CriticLayout:
    """The registered critics' layout; registration ends here."""
    global _LAYOUT
    if _LAYOUT is None:
        _LAYOUT = CriticLayout(tuple(_REGISTERED))
        # a critic from outside the package is not in the kernel cache's key: such a process caches apart
        key_cache_to_outside_critics([f for c in _LAYOUT.critics
                                      for f in (c.term, *((c.state.start, c.state.advance) if c.state else ()))])
    return _LAYOUT


@dataclass(frozen=True)
class Sums:
    """A task kind's summed and split terms, stage and terminal: `summed(c, cost_w, geo, at)` returns c plus the
    terms in registration order; `split(cost_w, geo, at, out)` adds each term to `out` at its critic's index
    (`CriticLayout.names` order)."""

    stage: Callable
    stage_split: Callable
    terminal: Callable
    terminal_split: Callable


def _chain(terms: tuple, jit: Callable, twin: Callable, weights0: int, label: str) -> tuple:
    """The summed and the split function of `terms` ((weight index, parameter index, state slot, term), ...),
    compiled by `jit` with each term replaced by `twin(term)`.

    Each is one function that calls every term in turn, written out as source (`_compiled`), not a chain of small
    functions each calling the next: numba inlines an `inline="always"` callee by running its untyped pipeline and
    copying its IR at every call site, so a chain of links cost one inline per link and term at every site (the
    kernels' largest compile cost). The sums are the same: the terms are added in registration order, each
    split term to its own slot, with the same operations."""
    names = {f"term{n}": twin(term) for n, (_wi, _pi, _si, term) in enumerate(terms)}
    calls = [f"term{n}(cost_w[{wi}], cost_w, {pi}, geo, at" + (f", at.state[{si}])" if si >= 0 else ")")
             for n, (wi, pi, si, _term) in enumerate(terms)]
    summed = ["def summed(c, cost_w, geo, at):", *[f"    c = c + {call}" for call in calls], "    return c"]
    split = ["def split(cost_w, geo, at, out):",
             *[f"    out[{wi - weights0}] += {call}" for (wi, _pi, _si, _t), call in zip(terms, calls, strict=True)],
             "    return None"]
    return (_compiled(jit, summed, names, f"{label} summed"), _compiled(jit, split, names, f"{label} split"))


def _compiled(jit: Callable, lines: list[str], names: Mapping[str, Callable], label: str) -> Callable:
    """`jit` of the one function whose source is `lines`, its global names bound to `names`."""
    scope = dict(names)
    exec(compile("\n".join(lines) + "\n", f"<critics: {label}>", "exec"), scope)  # noqa: S102 - our own source
    return jit(scope[lines[0].split()[1].split("(")[0]])


@dataclass(frozen=True)
class States:
    """The stateful critics' values as the drivers carry them, a tuple (`CriticLayout.stateful` order):
    `start(cost_w)` before a rollout's first step, `advance(state, cost_w)` after each step."""

    start: Callable
    advance: Callable


def build_states(jit: Callable | None = None, twin: Callable | None = None) -> States:
    """The state chains of the registered stateful critics, compiled as `build_sums`'s."""
    jit = jit or njit(fastmath=FASTMATH, inline="always")
    twin = twin or (lambda f: f)
    lay = layout()
    start = jit(lambda cost_w: ())
    advance = jit(lambda state, cost_w: ())
    for c in reversed(lay.stateful):
        pi, si = lay.first_param(c.name), lay.state_slot(c.name)
        start = _link_start(jit, twin(c.state.start), pi, start)
        advance = _link_advance(jit, twin(c.state.advance), pi, si, advance)
    return States(start, advance)


def _link_start(jit: Callable, first: Callable, pi: int, rest: Callable) -> Callable:
    def start(cost_w) -> tuple:  # noqa: ANN001 - an array, or a CUDA array
        return (first(cost_w, pi),) + rest(cost_w)

    return jit(start)


def _link_advance(jit: Callable, step: Callable, pi: int, si: int, rest: Callable) -> Callable:
    def advance(state: tuple, cost_w) -> tuple:  # noqa: ANN001 - an array, or a CUDA array
        return (step(state[si], cost_w, pi),) + rest(state, cost_w)

    return jit(advance)


def build_sums(jit: Callable | None = None, twin: Callable | None = None) -> dict[str, Sums]:
    """Each task kind's `Sums`, compiled by `jit` (default: njit with the kernels' flags, inlined in numba's IR like
    the terms), terms by `twin(term)`."""
    jit = jit or njit(fastmath=FASTMATH, inline="always")
    twin = twin or (lambda f: f)
    lay = layout()
    w0 = lay.weight_index(lay.names[0]) if lay.names else 0
    out = {}
    for task in TASK_KINDS:
        stage, stage_split = _chain(lay.terms(task, False), jit, twin, w0, f"{task} stage")
        terminal, terminal_split = _chain(lay.terms(task, True), jit, twin, w0, f"{task} terminal")
        out[task] = Sums(stage, stage_split, terminal, terminal_split)
    return out



@dataclass(frozen=True)
class ByKind:
    """The sums of whichever task kind a step's task is (`TaskBundle.kind`), so the kernels name no kind: `stage(kind,
    c, cost_w, geo, at)`, `stage_split(kind, cost_w, geo, at, out)` (and terminal alike) call that kind's `Sums`;
    `lane_stage(kind)` / `lane_terminal(kind)` say whether its stage / terminal critics read the lane at the step
    (`Step.lane_dist`, ...; the drivers query it once for all of them); `any_lane_terminal` whether any kind's
    terminal critics do (else the drivers build the terminal step without compiling a lane query).

    `stage_lane(kind, ...)` and `stage_plain(kind, ...)` are `stage` over the kinds whose stage critics read the lane
    and over the others: a driver that has already branched on `lane_stage` (the CPU kernel's `_add_costs`) calls
    each kind's chain once, not twice (an inlined chain is compiled at every call site)."""

    stage: Callable
    stage_split: Callable
    terminal: Callable
    terminal_split: Callable
    lane_stage: Callable
    lane_terminal: Callable
    stage_lane: Callable
    stage_plain: Callable
    any_lane_terminal: bool


def build_by_kind(sums: Mapping[str, Sums], jit: Callable | None = None) -> ByKind:
    """`ByKind` over each task kind's `sums` (`build_sums`, compiled by the same `jit`): a chain of `if kind == id`
    tests in `TASK_KINDS` order, the last kind taking any other id (`TaskBundle.args` refuses ids the kernels have no
    critics for), so LLVM sees the test the kernels once wrote by hand (seeded plans unchanged)."""
    jit = jit or njit(fastmath=FASTMATH, inline="always")
    lay = layout()
    ids = [TASK_KINDS[name] for name in sums]
    reads_lane = [name in LANE_TASK_KINDS for name in sums]
    reads_lane_end = [name in LANE_TASK_KINDS and bool(lay.terms(name, True)) for name in sums]

    def chain(link: Callable, tail: Callable, funcs: list, kinds: list[int] = ids) -> Callable:
        if not funcs:  # no kind of this group: never called (the drivers branch on `lane_stage` first)
            return jit(lambda kind, c, cost_w, geo, at: c)
        pick = tail(jit, funcs[-1])
        for kid, here in reversed(list(zip(kinds[:-1], funcs[:-1], strict=True))):
            pick = link(jit, kid, here, pick)
        return pick

    def group(lane: bool) -> Callable:
        kinds = [(kid, s.stage) for kid, s, reads in zip(ids, sums.values(), reads_lane, strict=True) if reads == lane]
        return chain(_pick_sum, _tail_sum, [f for _k, f in kinds], [k for k, _f in kinds])

    return ByKind(
        chain(_pick_sum, _tail_sum, [s.stage for s in sums.values()]),
        chain(_pick_split, _tail_split, [s.stage_split for s in sums.values()]),
        chain(_pick_sum, _tail_sum, [s.terminal for s in sums.values()]),
        chain(_pick_split, _tail_split, [s.terminal_split for s in sums.values()]),
        chain(_pick_flag, _tail_flag, reads_lane),
        chain(_pick_flag, _tail_flag, reads_lane_end),
        group(True),
        group(False),
        any(reads_lane_end),
    )


def _tail_sum(jit: Callable, last: Callable) -> Callable:
    def pick(kind: int, c: float, cost_w, geo: tuple, at: tuple) -> float:  # noqa: ANN001 - an array
        return last(c, cost_w, geo, at)

    return jit(pick)


def _pick_sum(jit: Callable, kid: int, here: Callable, rest: Callable) -> Callable:
    def pick(kind: int, c: float, cost_w, geo: tuple, at: tuple) -> float:  # noqa: ANN001 - an array
        if kind == kid:
            return here(c, cost_w, geo, at)
        return rest(kind, c, cost_w, geo, at)

    return jit(pick)


def _tail_split(jit: Callable, last: Callable) -> Callable:
    def pick(kind: int, cost_w, geo: tuple, at: tuple, out) -> None:  # noqa: ANN001 - arrays
        last(cost_w, geo, at, out)

    return jit(pick)


def _pick_split(jit: Callable, kid: int, here: Callable, rest: Callable) -> Callable:
    def pick(kind: int, cost_w, geo: tuple, at: tuple, out) -> None:  # noqa: ANN001 - arrays
        if kind == kid:
            here(cost_w, geo, at, out)
        else:
            rest(kind, cost_w, geo, at, out)

    return jit(pick)


def _tail_flag(jit: Callable, last: bool) -> Callable:
    def pick(kind: int) -> bool:
        return last

    return jit(pick)


def _pick_flag(jit: Callable, kid: int, here: bool, rest: Callable) -> Callable:
    def pick(kind: int) -> bool:
        if kind == kid:
            return here
        return rest(kind)

    return jit(pick)
