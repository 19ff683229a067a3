"""terrain: the online terrain-weight estimator. Keeps (state, applied command, next state) triples from
consecutive states and the base commands between them, solves for convex weights, publishes `terrain/weights`.

Off the control path: it solves after the planner has answered a state (not alongside it), and comes up
publishing the prior before it builds its solver (cvxpy), the slow part of its start."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np
from pydantic import Field

from gpmppi.terrain_config import EstimatorConfig
from schemas import State, TerrainWeights
from services.convert import state_to_array
from services.node import Node, NodeSettings

if TYPE_CHECKING:
    from gpmppi.gp.model_file import GPModel
    from gpmppi.terrain import BayesTerrainEstimator, TerrainEstimator


class Settings(NodeSettings):
    service: str = Field("terrain", description="service name")
    model_file: str | None = Field(None, description="GP model file (None: the shipped model)")
    estimator: EstimatorConfig = Field(
        default_factory=EstimatorConfig, description="the estimator: method ('bayes', the default, or the paper's "
        "convex problem 'paper') and its parameters (gpmppi.terrain_config.EstimatorConfig)"
    )
    dt: float = Field(0.1, gt=0, description="expected time between states (the GP model's step) [s]")
    dt_tolerance: float = Field(0.5, gt=0, description="skip pairs whose spacing differs from dt by more (fraction)")
    command_source: str = Field("base_cmd", description="'base_cmd' (what the base got) or 'cmd' (planner output)")
    command_wait_s: float = Field(
        0.05, ge=0, description="solve once the command for the newest state has arrived, or after this long [s]"
    )


def run(settings: Settings) -> int:
    # not services.planner's loader: that module imports the planner (its kernels) for nothing here
    from gpmppi.gp.model_file import GPModel, load_default_model

    model = load_default_model() if settings.model_file is None else GPModel.load(settings.model_file)
    terrains = list(model.terrains)
    estimator: TerrainEstimator | BayesTerrainEstimator | None = None
    with Node(settings) as node:
        out = node.publisher("terrain_weights")
        states = node.subscribe("state", newest_only=False, capacity=64)
        command_sub = node.subscribe(settings.command_source, newest_only=False, capacity=64)
        # commands carry the stamp of the state they were planned from (egress keeps it), so the command applied
        # over the transition from the state stamped t_k is the one stamped t_k: pairing by stamp, not by arrival
        # order, stays right when this loop runs late and the next command has already arrived
        commands: dict[int, np.ndarray] = {}
        previous = None  # (stamp_ns, state array)
        pending: list[State] = []
        pending_since = 0.0
        while node.ok():
            for c in command_sub.drain():
                u = [c.v, c.omega] if settings.command_source == "base_cmd" else [c.v_ref, c.omega_ref]
                commands[c.header.stamp_ns] = np.array(u)
            if new := states.drain():
                pending_since = pending_since if pending else time.monotonic()
                pending += new
            if not pending:
                node.spin_once()
                continue
            if estimator is None:
                # up at once with the prior (uniform weights, solver_ok False: what the planner uses without us,
                # and what a short history gives), then the slow part of the start: cvxpy and the problem (the paper's
                # method) or the GP predictor
                out.put(_weights_message(terrains, np.full(len(terrains), 1 / len(terrains)), False, 0.0, pending))
                node.cycle()
                estimator = _estimator(model, settings)
                continue
            # the state's own command arrives when the planner is done with it: solving then, not alongside the
            # planner, keeps this service off the cores the control path needs (it gets the same weights a cycle on)
            waited = time.monotonic() - pending_since
            if pending[-1].header.stamp_ns not in commands and waited < settings.command_wait_s:
                node.spin_once(settings.command_wait_s - waited)
                continue
            for msg in pending:
                x = state_to_array(msg)
                stamp = msg.header.stamp_ns
                if previous is not None:
                    gap = (stamp - previous[0]) / 1e9
                    command = commands.get(previous[0])
                    if command is not None and abs(gap - settings.dt) <= settings.dt_tolerance * settings.dt:
                        estimator.observe(previous[1], command, x)
                previous = (stamp, x)
            # keep only commands that a later transition can still use
            for old in [t for t in commands if t < previous[0]]:
                del commands[old]
            est = estimator.estimate()
            weights = np.clip(np.asarray(est.weights, dtype=np.float64), 0.0, 1.0)
            weights = weights / weights.sum() if weights.sum() > 0 else np.full(len(terrains), 1 / len(terrains))
            residual = max(0.0, float(est.residual)) if np.isfinite(est.residual) else 0.0
            # a short history is the normal warm-up, not a failure worth an error line
            if not est.ok and len(estimator) >= estimator.min_history:
                node.error(f"weight solve: {est.message}")
            out.put(_weights_message(terrains, weights, bool(est.ok), residual, pending))
            pending = []
            node.cycle()
            node.spin_once(0.0)
    return 0


def _estimator(model: GPModel, settings: Settings) -> TerrainEstimator | BayesTerrainEstimator:
    from gpmppi.terrain import make_estimator

    return make_estimator(model, settings.estimator)


def _weights_message(
    terrains: list[str], weights: np.ndarray, ok: bool, residual: float, states: list[State]
) -> TerrainWeights:
    msg = TerrainWeights(names=terrains, weights=weights.tolist(), solver_ok=ok, residual=residual)
    msg.header.stamp_ns = states[-1].header.stamp_ns
    return msg
