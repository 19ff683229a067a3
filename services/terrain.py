"""terrain: the online terrain-weight estimator. Keeps (state, applied command, next state) triples from
consecutive states and the base commands between them, solves for convex weights, publishes `terrain/weights`."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from schemas import TerrainWeights
from services.convert import state_to_array
from services.node import Node, NodeSettings


class Settings(NodeSettings):
    service: str = Field("terrain", description="service name")
    model_file: str | None = Field(None, description="GP model file (None: the shipped model)")
    history: int = Field(20, ge=1, description="steps H kept for the weight problem")
    gamma: float = Field(
        0.1, ge=0, description="L1 weight on changes of the weights between solves (in units of the fit: the mean "
        "squared velocity residual per step divided by the model's noise variance)"
    )
    dt: float = Field(0.1, gt=0, description="expected time between states (the GP model's step) [s]")
    dt_tolerance: float = Field(0.5, gt=0, description="skip pairs whose spacing differs from dt by more (fraction)")
    command_source: str = Field("base_cmd", description="'base_cmd' (what the base got) or 'cmd' (planner output)")


def run(settings: Settings) -> int:
    from gpmppi.terrain import TerrainEstimator
    from services.planner import load_model

    model = load_model(settings.model_file)
    estimator = TerrainEstimator(model, history=settings.history, gamma=settings.gamma)
    with Node(settings) as node:
        out = node.publisher("terrain_weights")
        states = node.subscribe("state", newest_only=False, capacity=64)
        command_sub = node.subscribe(settings.command_source, newest_only=False, capacity=64)
        # commands carry the stamp of the state they were planned from (egress keeps it), so the command applied
        # over the transition from the state stamped t_k is the one stamped t_k: pairing by stamp, not by arrival
        # order, stays right when this loop runs late and the next command has already arrived
        commands: dict[int, np.ndarray] = {}
        previous = None  # (stamp_ns, state array)
        while node.ok():
            for c in command_sub.drain():
                u = [c.v, c.omega] if settings.command_source == "base_cmd" else [c.v_ref, c.omega_ref]
                commands[c.header.stamp_ns] = np.array(u)
            new_states = states.drain()
            if not new_states:
                node.spin_once()
                continue
            for msg in new_states:
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
            weights = (
                weights / weights.sum() if weights.sum() > 0 else np.full(len(model.terrains), 1 / len(model.terrains))
            )
            msg_out = TerrainWeights(
                names=list(model.terrains),
                weights=weights.tolist(),
                solver_ok=bool(est.ok),
                residual=max(0.0, float(est.residual)) if np.isfinite(est.residual) else 0.0,
            )
            msg_out.header.stamp_ns = new_states[-1].header.stamp_ns
            # a short history is the normal warm-up, not a failure worth an error line
            if not est.ok and len(estimator) >= estimator.min_history:
                node.error(f"weight solve: {est.message}")
            out.put(msg_out)
            node.cycle()
            node.spin_once(0.0)
    return 0
