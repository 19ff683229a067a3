"""terrain: the online terrain-weight estimator. An event loop over `gpmppi.terrain.cycle.TerrainCycle` (pairing
states with the commands the base received, dt gating, the estimator, clean-up; the closed-loop evaluation drives
the same cycle): decode states and commands, cycle, encode `terrain/weights`.

Off the control path: it solves after the planner has answered a state (not alongside it), and comes up
publishing the prior before it builds its solver (cvxpy), the slow part of its start."""

from __future__ import annotations

import sys
import time
from typing import TYPE_CHECKING

import numpy as np
from pydantic import Field

from gpmppi.terrain.cycle import TerrainCycle, TerrainCycleConfig, WeightsUpdate
from gpmppi.terrain.learning import GroundLearning, LearnConfig, TeeEstimator
from gpmppi.terrain.settings import EstimatorConfig
from schemas import BaseCommand, Command, GroundLearn, TerrainWeights
from services.codec.convert import state_to_array
from services.runtime.node import Node
from services.runtime.node_settings import NodeSettings

if TYPE_CHECKING:
    from gpmppi.gp.model_file import GPModel
    from gpmppi.terrain.estimate import EstimatorLike


class Settings(NodeSettings, TerrainCycleConfig):
    """The terrain service's settings: the cycle's (`TerrainCycleConfig`: dt, dt_tolerance, command_source,
    command_wait_s), the estimator's and the model file."""

    service: str = Field("terrain", description="service name")
    model_file: str | None = Field(None, description="the robot profile (.npz from `gpmppi train`; a launch "
                                   "file's top-level `profile` fills it; None: the shipped Jackal profile)")
    estimator: EstimatorConfig = Field(
        default_factory=EstimatorConfig, description="the estimator: method ('bayes', the default, or the paper's "
        "convex problem 'paper') and its parameters (gpmppi.terrain.settings.EstimatorConfig)"
    )
    learn: LearnConfig = Field(
        default_factory=LearnConfig, description="learning a new ground while driving: when, how, where it is saved "
        "(gpmppi.terrain.learning.LearnConfig)"
    )


def command_array(msg: BaseCommand | Command) -> list[float]:
    """What the command says was (to be) applied: a base command's output, or a planner command's reference."""
    return [msg.v, msg.omega] if isinstance(msg, BaseCommand) else [msg.v_ref, msg.omega_ref]


def run(settings: Settings) -> int:
    # not services.planner's loader: that module imports the planner (its kernels) for nothing here
    from gpmppi.gp.model_file import GPModel, ModelFileError, load_default_model
    from gpmppi.terrain.settings import profile_calibration

    try:
        model = load_default_model() if settings.model_file is None else GPModel.load(settings.model_file)
        if settings.estimator.method == "bayes":  # a profile without the calibration its settings need: one line
            profile_calibration(settings.estimator, model)
    except ModelFileError as exc:
        print(f"gpmppi service terrain: {exc}", file=sys.stderr)
        return 2
    # the estimator's modules (cvxpy for the paper's method) before the session: a process started ahead of need
    # waits in `Node.open` with them imported (services.runtime.role)
    import gpmppi.terrain.estimator  # noqa: F401

    if settings.estimator.method == "paper":
        import cvxpy  # noqa: F401

    with Node(settings) as node:
        return serve(node, settings, model)


def serve(node: Node, settings: Settings, model: GPModel, estimator: EstimatorLike | None = None) -> int:
    """The terrain service's event loop on an open node, until it is stopped: decode, `TerrainCycle`, encode.
    `estimator`: one already built (None: built after the first prior is out, as the service starts)."""
    from gpmppi.gp.online_ground import model_version
    from services.terrain_learning import Learner

    terrains = list(model.terrains)
    learning = GroundLearning(model, settings.learn)
    learner = Learner(learning, settings.learn.save_to or settings.model_file, model_version(model))
    cycle = TerrainCycle(TerrainCycleConfig.from_settings(settings), len(terrains),
                         None if estimator is None else TeeEstimator(estimator, learning))
    out = node.publisher("terrain_weights")
    updates = node.publisher("model_update")
    learn_sub = node.subscribe("ground_learn", newest_only=False, capacity=16)
    states = node.subscribe("state", newest_only=False, capacity=64)
    command_sub = node.subscribe(settings.command_source, newest_only=False, capacity=64)
    # a predecessor's last weights (the launcher saw them): published first instead of the prior, and the
    # estimator starts from them
    resumed = _resumed_weights(node, terrains)
    unknown = UnknownReport(node)
    try:
        while node.ok():
            for request in learn_sub.drain():
                _on_learn_request(node, learning, learner, request)
            new_model, update_msg, line = learner.poll()
            if new_model is not None and update_msg is not None:
                # the learned ground joins: the estimator over the new grounds, the weights published by their names
                model, terrains = new_model, list(new_model.terrains)
                cycle.n_terrains = len(terrains)
                cycle.estimator = TeeEstimator(_swapped_estimator(new_model, settings, unknown.active), learning)
                updates.put(update_msg)
                node.log.info("model version %d: %s (saved to %s)", update_msg.version, line, update_msg.path)
            elif line is not None:
                node.error(line)
            sent = _serve_once(node, settings, model, cycle, learning, out, states, command_sub, terrains, resumed,
                               unknown)
            resumed = None if cycle.estimator is not None else resumed
            # new ground noticed (the novelty test's P(unknown), held above the threshold) starts the learning too
            if sent is not None and learner.path is not None:
                if (line := learning.on_unknown(sent.unknown, time.monotonic())) is not None:
                    node.log.info(line)
            if (started := learner.submit_ready()) is not None:
                node.log.info(started)
    finally:
        learner.close()
    return 0


def _on_learn_request(node: Node, learning: GroundLearning, learner, request: GroundLearn) -> None:  # noqa: ANN001
    """A GroundLearn request: start or cancel, logged in one line (refused when there is no file to save to)."""
    if request.action == "cancel":
        node.log.info(learning.cancel())
    elif learner.path is None:
        node.reject("ground_learn: the service runs the shipped profile and has no file to save a learned ground to; "
                    "set model_file (a launch file's profile) or learn.save_to")
    else:
        node.log.info(learning.start(request.name))


def _serve_once(node: Node, settings: Settings, model: GPModel, cycle: TerrainCycle, learning: GroundLearning,
                out, states, command_sub, terrains: list[str], resumed: np.ndarray | None,  # noqa: ANN001
                unknown: UnknownReport) -> TerrainWeights | None:
    """One pass of the loop: take states and commands, solve when due, publish the weights over `terrains`; the
    solved weights' message, if one went out."""
    received_ns = time.time_ns()  # the loop wakes on arrival: when the base got them, on the states' clock
    for c in command_sub.drain():
        cycle.on_command(c.header.stamp_ns, command_array(c))
        if isinstance(c, BaseCommand):
            cycle.on_output(received_ns, command_array(c))
    if new := states.drain():
        cycle.on_states([(m.header.stamp_ns, state_to_array(m)) for m in new], time.monotonic())
    if not cycle.pending:
        node.spin_once()
        return None
    if cycle.estimator is None:
        # up at once with the prior (uniform weights, solver_ok False: what the planner uses without us,
        # and what a short history gives), then the slow part of the start: cvxpy and the problem (the paper's
        # method) or the GP predictor
        first = cycle.prior_update(settings.estimator.names_top_at_start)
        if resumed is not None:  # the estimator restarts from them with no leader: they name a top as the prior does
            first = WeightsUpdate(resumed, False, 0.0, first.stamp_ns, identified=first.identified)
        out.put(_weights_message(terrains, first))
        node.cycle()
        cycle.estimator = TeeEstimator(_estimator(model, settings), learning)
        if resumed is not None:
            cycle.estimator.reset(resumed)
            node.log.info("resumed from the last published weights", extra={"fields": {
                "weights": [round(w, 3) for w in resumed.tolist()]}})
        return None
    # the state's own command arrives when the planner is done with it: solving then, not alongside the
    # planner, keeps this service off the cores the control path needs (it gets the same weights a cycle on)
    wait = cycle.wait_s(time.monotonic())
    if wait > 0.0:
        node.spin_once(wait)
        return None
    update = cycle.solve()
    if update.error is not None:
        node.error(update.error)
    unknown.report(update, terrains)
    msg = _weights_message(terrains, update)
    out.put(msg)
    node.cycle()
    node.spin_once(0.0)
    return msg


def _resumed_weights(node: Node, terrains: list[str]) -> np.ndarray | None:
    """The predecessor's last weights in the model's terrain order, if handed over and for these terrains."""
    last = node.handed_over("terrain_weights", TerrainWeights)
    if last is None:
        return None
    if sorted(last.names) != sorted(terrains):
        node.log.warning("handed-over weights are for other terrains %s: starting from the prior", last.names)
        return None
    by_name = dict(zip(last.names, last.weights, strict=True))
    w = np.clip(np.array([by_name[t] for t in terrains], dtype=np.float64), 0.0, 1.0)
    return w / w.sum() if w.sum() > 0 else None


def _estimator(model: GPModel, settings: Settings) -> EstimatorLike:
    from gpmppi.terrain.estimator import make_estimator

    return make_estimator(model, settings.estimator)


def _swapped_estimator(model: GPModel, settings: Settings, unknown: bool) -> EstimatorLike:
    """The estimator over a model with a learned ground. If the ground was unknown when it came, it stays so until
    the new model has explained a whole window: a new estimator starts from the prior, and deciding "known" at once
    named the prior's first ground (asphalt) in the "known again" log and event instead of the learned one."""
    est = _estimator(model, settings)
    hold = getattr(est, "hold_unknown", None)
    if unknown and hold is not None:
        hold()
    return est


class UnknownReport:
    """"None of these grounds" into the health: the heartbeat's flag `unknown_ground` (the hysteretic decision),
    its flag `unknown_free_run` (the decision is set and the free-run channel, a loss of grip, gives P(unknown); set
    with `unknown_ground` clear: the one-step channel), its counter `unknown_permille` (the last P(unknown) x 1000) and
    `unknown_entered` (how often it was set), and a log line each time the decision changes."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.active = False
        with node.counters.lock:
            node.counters.flags["unknown_ground"] = False
            node.counters.flags["unknown_free_run"] = False

    def report(self, update: WeightsUpdate, terrains: list[str]) -> None:
        c = self.node.counters
        with c.lock:
            c.counts["unknown_permille"] = round(1000 * update.unknown)
            c.flags["unknown_ground"] = update.unknown_active
            c.flags["unknown_free_run"] = update.unknown_active and update.unknown_channel == "free-run"
        if update.unknown_active == self.active:
            return
        self.active = update.unknown_active
        nearest = terrains[int(np.argmax(update.weights))]
        if self.active:
            c.count("unknown_entered")
            # the free-run channel sees a slide (grip lost), the one-step one a ground that drags or turns otherwise
            how = (" (free-run channel: the robot does not follow the commands as any trained ground would, a loss "
                   "of grip)" if update.unknown_channel == "free-run" else "")
            self.node.log.warning(f"ground unknown: no trained ground explains the last steps{how} (P(unknown) "
                                  f"{update.unknown:.2f}; nearest {nearest})")
        else:
            self.node.log.info(f"ground known again (P(unknown) {update.unknown:.2f}; {nearest})")


def _weights_message(terrains: list[str], update: WeightsUpdate) -> TerrainWeights:
    msg = TerrainWeights(names=terrains, weights=update.weights.tolist(), solver_ok=update.ok,
                         residual=update.residual, unknown=update.unknown, unknown_active=update.unknown_active,
                         unknown_channel=update.unknown_channel, identified=update.identified)
    msg.header.stamp_ns = update.stamp_ns
    return msg
