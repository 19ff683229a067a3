"""What a recording of new ground in the running stack shows (docs/new_ground.md, "In the stack"): when the sim's
ground changed, when the terrain service first said `unknown` > 0.5, when a learned ground was announced
(`ModelUpdate`), when the weights first named it and its weight from then on, and the lane RMSE before the change,
while the ground was new and after the model update.

    python -m tools.new_ground_timeline runs/ng.mcap [--lane circle] [--json]

Times are seconds from the first `terrain/label` in the recording (the sim's first published state)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from gpmppi.scenarios import lane_scenario
from gpmppi.tasks import distance_to_polyline
from schemas import ModelUpdate, State, TerrainLabel, TerrainWeights

SETTLE_S = 5.0  # the first seconds of driving (the start from rest) and of each phase are left out of its RMSE


def _rmse_mm(t: np.ndarray, d: np.ndarray, t0: float, t1: float) -> float | None:
    sel = d[(t >= t0) & (t < t1)]
    return None if sel.size < 10 else round(float(np.sqrt(np.mean(sel * sel)) * 1e3), 1)


def timeline(path: str | Path, robot: str = "jackal", lane: str = "circle") -> dict:
    """The new-ground timeline of the recording at `path` (see the module's text); None where it did not happen."""
    from services.recording.mcap_io import read_messages

    keys = {f"gpmppi/{robot}/{k}": k for k in ("terrain/label", "terrain/weights", "model", "odom/raw")}
    labels: list[tuple[int, str]] = []
    weights: list[tuple[int, TerrainWeights]] = []
    updates: list[tuple[int, ModelUpdate]] = []
    states: list[tuple[int, float, float, float]] = []
    for key, t_ns, msg in read_messages(path, keys):
        kind = keys[key]
        if kind == "terrain/label" and isinstance(msg, TerrainLabel):
            labels.append((t_ns, msg.terrain))
        elif kind == "terrain/weights" and isinstance(msg, TerrainWeights):
            weights.append((t_ns, msg))
        elif kind == "model" and isinstance(msg, ModelUpdate):
            updates.append((t_ns, msg))
        elif kind == "odom/raw" and isinstance(msg, State):
            states.append((t_ns, msg.x, msg.y, msg.v))
    if not labels:
        raise ValueError(f"{path}: no gpmppi/{robot}/terrain/label messages; record a launch with a sim")
    t0 = labels[0][0]

    def s(t_ns: int) -> float:
        return round((t_ns - t0) * 1e-9, 2)

    change = next(((t, g) for t, g in labels if g != labels[0][1]), None)
    t_change = s(change[0]) if change else None
    flagged = next(((t, w) for t, w in weights if w.unknown > 0.5 and (change is None or t >= change[0])), None)
    unknown = s(flagged[0]) if flagged else None
    update = updates[0] if updates else None
    learned = update[1].learned if update else None
    named = [(t, w) for t, w in weights if learned and learned in w.names]
    after_named = [w.weights[w.names.index(learned)] for _, w in named] if learned else []
    late = after_named[len(after_named) // 2:]  # the second half: once the filter has moved its weight over
    task = lane_scenario(lane).task
    st = np.array(states, dtype=np.float64).reshape(-1, 4)
    t = (st[:, 0] - t0) * 1e-9
    d = distance_to_polyline(st[:, 1:3], np.asarray(task.centerline), task.closed)
    moving = t[st[:, 3] > 0.5]
    t_drive = float(moving[0]) if moving.size else 0.0
    t_update = s(update[0]) if update else None
    end = float(t[-1]) if t.size else 0.0
    return {
        "recording": str(path),
        "start_ground": labels[0][1],
        "ground_changed_s": t_change,
        "new_ground": change[1] if change else None,
        "driving_from_s": round(t_drive, 2),
        "first_unknown_over_half_s": unknown,
        "unknown_delay_s": None if unknown is None or t_change is None else round(unknown - t_change, 2),
        # the novelty test's channel that flagged it ('' in recordings made before the messages said it)
        "unknown_channel": flagged[1].unknown_channel if flagged else None,
        "model_update_s": t_update,
        "learned": learned,
        "learned_samples": update[1].samples if update else None,
        "model_version": update[1].version if update else None,
        "first_weights_naming_it_s": s(named[0][0]) if named else None,
        "learned_weight_mean_second_half": round(float(np.mean(late)), 3) if late else None,
        "learned_weight_final": round(after_named[-1], 3) if after_named else None,
        "rmse_before_mm": _rmse_mm(t, d, t_drive + SETTLE_S, t_change if t_change is not None else end),
        "rmse_new_before_update_mm": None if t_change is None else _rmse_mm(
            t, d, t_change, t_update if t_update is not None else end),
        "rmse_after_update_mm": None if t_update is None else _rmse_mm(t, d, t_update + SETTLE_S, end),
        "end_s": round(end, 2),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.new_ground_timeline", description=__doc__.split("\n")[0])
    parser.add_argument("recording")
    parser.add_argument("--robot", default="jackal")
    parser.add_argument("--lane", default="circle", help="the lane driven (its centre line gives the RMSE)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    try:
        result = timeline(args.recording, args.robot, args.lane)
    except (FileNotFoundError, ValueError, KeyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        for k, v in result.items():
            print(f"{k}: {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
