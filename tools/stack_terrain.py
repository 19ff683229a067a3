"""Replay a stack recording's states and commands through the in-process terrain cycle, step by step.

    python -m tools.stack_terrain runs/asphalt.mcap [--json] [--profile robot.npz]

From the log: states, the planner's commands (`cmd`), what the base received (`base/cmd`, with the recorder's
arrival time), the terrain service's published weights and the sim's terrain label. Replays, each a fresh
`TerrainCycle` with the robot profile (`--profile`; default the shipped Jackal's) and the default estimator:

- `stack`: `command_source: base_cmd`, `pairing: stamp`: what the terrain service ran before `pairing: applied`
  became the default (set `pairing: stamp` in the launch to check a new log against it); its weights are compared
  with the recorded ones state by state (the replay is faithful when they agree);
- `cmd`: the planner's command paired by stamp (the in-process estimator's pairing before the deployed path);
- `applied`: the time average of the base's outputs over each transition, by their arrival at the recorder.

For each: the weight on the true terrain after the first 3 s (time-averaged), top-terrain changes per minute after
3 s (counted between weights that name a top, `TerrainWeights.identified`) and the share of that time with no top
named; for the recorded weights also the novelty test's false alarms (the share of the time on trained ground with
P(unknown) > 0.5, the evaluation's `unknown_share`, and with `unknown_active`, the planner's caution on); and the
latency of each state's command at the base (first base output's arrival - the state's stamp).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from gpmppi.evaluation.metrics import (
    true_weight_mean,
    unidentified_share,
    unknown_share,
    weight_switches_per_min,
)
from gpmppi.gp.model_file import GPModel, load_default_model
from gpmppi.terrain.cycle import TerrainCycle, TerrainCycleConfig
from gpmppi.terrain.estimator import make_estimator
from gpmppi.terrain.settings import EstimatorConfig
from services.recording.mcap_io import read_messages


def load(path: Path) -> dict:
    """The log's states, commands, base outputs, weights (and their P(unknown) and `unknown_active`) and terrain
    labels, in log order."""
    out: dict = {"states": [], "cmds": [], "base": [], "weights": [], "unknown": [], "labels": []}
    for key, log_ns, msg in read_messages(path):
        name = key.split("/", 2)[2]
        if name == "state":
            out["states"].append((msg.header.stamp_ns, log_ns, np.array(msg.as_array())))
        elif name == "cmd":
            out["cmds"].append((msg.header.stamp_ns, log_ns, np.array([msg.v_ref, msg.omega_ref])))
        elif name == "base/cmd":
            out["base"].append((msg.header.stamp_ns, log_ns, np.array([msg.v, msg.omega]), msg.reason))
        elif name == "terrain/weights":
            out["weights"].append((msg.header.stamp_ns, dict(zip(msg.names, msg.weights, strict=True)),
                                   msg.identified))
            out["unknown"].append((msg.header.stamp_ns, msg.unknown, msg.unknown_active))
        elif name == "terrain/label":
            out["labels"].append((log_ns, msg.terrain))
    return out


def replay(log: dict, config: TerrainCycleConfig, model: GPModel,
           estimator: EstimatorConfig | None = None) -> tuple[dict[int, np.ndarray], dict[int, bool]]:
    """Weights after each state (by stamp), and whether they named a top ground, the inputs fed in their recorded
    arrival order."""
    terrains = list(model.terrains)
    cycle = TerrainCycle(config, len(terrains), make_estimator(model, estimator or EstimatorConfig()))
    events = [(ns, 0, s) for s, ns, _ in log["states"]]
    source = log["base"] if config.command_source == "base_cmd" else log["cmds"]
    events += [(ns, 1, i) for i, (_, ns, *_) in enumerate(source)]
    states = {s: x for s, _, x in log["states"]}
    weights: dict[int, np.ndarray] = {}
    identified: dict[int, bool] = {}
    for ns, kind, ref in sorted(events, key=lambda e: (e[0], e[1])):
        if kind == 1:
            stamp, _, u, *_ = source[ref]
            cycle.on_command(stamp, u)
            if config.command_source == "base_cmd":
                cycle.on_output(ns, u)
        else:
            cycle.on_states([(ref, states[ref])], ns / 1e9)
        if cycle.pending and cycle.wait_s(ns / 1e9) == 0.0:
            update = cycle.solve()
            weights[update.stamp_ns] = update.weights
            identified[update.stamp_ns] = update.identified
    return weights, identified


def scores(stamps: list[int], weights: dict[int, np.ndarray], truth: list[str], terrains: list[str],
           identified: dict[int, bool]) -> dict:
    """The weight on the true terrain after the first 3 s, the top-terrain changes a minute after 3 s (counted
    between weights that name a top: `TerrainWeights.identified`), the share of that time with no top named, and
    the mean weights after the first 30 states."""
    keep = [i for i, s in enumerate(stamps) if s in weights]
    w = np.array([weights[stamps[i]] for i in keep])
    named = np.array([identified.get(stamps[i], True) for i in keep], dtype=bool)
    t = np.array([(stamps[i] - stamps[0]) / 1e9 for i in keep] + [(stamps[keep[-1]] - stamps[0]) / 1e9 + 0.1])
    return {"true_weight_mean": true_weight_mean(t, w, [truth[i] for i in keep], terrains),
            "switches_per_min": weight_switches_per_min(t, w, identified=named),
            "top_unidentified_share": unidentified_share(t, named),
            "mean_weights": np.mean(w[30:], axis=0).round(3).tolist()}


def novelty_scores(stamps: list[int], unknown: list[tuple[int, float, bool]], truth: list[str],
                   terrains: list[str]) -> dict:
    """The novelty test's false alarms in the recorded weights, over the whole launch (the evaluation's
    `unknown_share`: the share of the time on trained grounds with P(unknown) > 0.5), and the share with the ground
    taken as unknown (`unknown_active`: the planner's caution on)."""
    by_stamp = {s: (u, active) for s, u, active in unknown}
    keep = [i for i, s in enumerate(stamps) if s in by_stamp]
    if not keep:
        return {"unknown_share": None, "unknown_active_share": None}
    u = np.array([by_stamp[stamps[i]][0] for i in keep])
    active = np.array([by_stamp[stamps[i]][1] for i in keep], dtype=np.float64)
    t = np.array([(stamps[i] - stamps[0]) / 1e9 for i in keep] + [(stamps[keep[-1]] - stamps[0]) / 1e9 + 0.1])
    driven = [truth[i] for i in keep]
    return {"unknown_share": unknown_share(t, u, driven, terrains),
            "unknown_active_share": unknown_share(t, active, driven, terrains)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.stack_terrain", description=__doc__.split("\n")[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--profile", type=Path, help="robot profile the stack ran with (default: the shipped one)")
    args = parser.parse_args(argv)
    log = load(args.log)
    model = load_default_model() if args.profile is None else GPModel.load(args.profile)
    terrains = list(model.terrains)
    stamps = [s for s, _, _ in log["states"]]
    labels = log["labels"]
    truth = []
    for _, ns, _ in log["states"]:
        before = [name for t, name in labels if t <= ns]
        truth.append(before[-1] if before else (labels[0][1] if labels else ""))
    recorded = {s: np.array([w[n] for n in terrains]) for s, w, _ in log["weights"]}
    recorded_named = {s: named for s, _, named in log["weights"]}
    result: dict = {"states": len(stamps), "terrain": sorted(set(truth)), "terrains": terrains}
    first: dict[int, int] = {}
    state_stamps = set(stamps)
    for stamp, ns, *_ in log["base"]:
        if stamp in state_stamps:
            first.setdefault(stamp, ns)
    lat = np.array([(first[s] - s) / 1e6 for s in stamps if s in first])
    result["state_to_base_ms"] = {"p10": float(np.percentile(lat, 10)), "p50": float(np.median(lat)),
                                  "p90": float(np.percentile(lat, 90)), "n": int(lat.size)}
    result["recorded"] = scores(stamps, recorded, truth, terrains, recorded_named)
    result["recorded"].update(novelty_scores(stamps, log["unknown"], truth, terrains))
    configs = (("stack", TerrainCycleConfig(pairing="stamp")), ("cmd", TerrainCycleConfig(command_source="cmd")),
               ("applied", TerrainCycleConfig(pairing="applied")))
    for name, cfg in configs:
        w, named = replay(log, cfg, model)
        result[name] = scores(stamps, w, truth, terrains, named)
        if name == "stack":
            both = [s for s in stamps if s in w and s in recorded]
            diff = np.array([np.max(np.abs(w[s] - recorded[s])) for s in both])
            result["stack_vs_recorded"] = {"compared": len(both), "max_abs": float(diff.max()),
                                           "p90_abs": float(np.percentile(diff, 90))}
    if args.json:
        print(json.dumps(result, default=float))
    else:
        for k, v in result.items():
            print(f"{k}: {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
