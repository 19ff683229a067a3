"""`gpmppi evaluate`'s command-line options, shared by its commands (`tools/evaluate.py`), and the parsing of the
repeated ones (`--switch`, `--set`)."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from tools.choices import ModelName
from tools.cli_checks import OUT_DIR, fail


class PlantName(str, Enum):
    physics = "physics"
    residual_net = "residual-net"


TerrainOpt = Annotated[list[str] | None, typer.Option("--terrain", "-t", help="Terrain(s) to drive on (repeat).")]
ModelOpt = Annotated[list[ModelName] | None, typer.Option("--model", "-m", help="Planner model(s) (repeat).")]
TrialsOpt = Annotated[
    int | None,
    typer.Option("--trials", "-n", min=1,
                 help="Trials per cell (different seeds); default 100 per scene and, in `table`, 3 per lane."),
]
SeedOpt = Annotated[int, typer.Option("--seed", min=0, help="First seed; trial i uses seed + i.")]
PlantOpt = Annotated[PlantName, typer.Option("--plant", help="physics (default) or the paper's residual-net.")]
PlantFileOpt = Annotated[Path | None, typer.Option("--plant-file", help="Residual-net JSON (e.g. fcnn.json).")]
TerrainFileOpt = Annotated[Path | None, typer.Option("--terrain-file", help="Terrain set YAML for the physics plant.")]
SceneFileOpt = Annotated[list[Path] | None, typer.Option("--scene-file", help="Obstacle scene YAML (repeat).")]
LaneFileOpt = Annotated[list[Path] | None, typer.Option("--lane-file", help="Lane YAML (repeat).")]
ProfileOpt = Annotated[Path | None, typer.Option(
    "--profile", help="Robot profile from `gpmppi train` (default: the shipped Jackal profile).")]
QuickOpt = Annotated[bool, typer.Option("--quick", help="Reduced run: one terrain, few trials, 25 m of lane.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print one JSON object {results: {task: {terrain: {model}}}}.")]
OutOpt = Annotated[
    Path | None,
    typer.Option("--output", "-o", metavar=OUT_DIR,
                 help="Write table, CSV, JSON and figures into this folder (`table`: default evaluation/)."),
]
ForceOpt = Annotated[bool, typer.Option("--force", help="Write into an --output folder that already holds files.")]
WorkersOpt = Annotated[
    int, typer.Option("--workers", "-j", min=1, max=256, help="Worker processes (without --ray).")
]
RayOpt = Annotated[
    str | None,
    typer.Option("--ray", metavar="auto|ADDRESS",
                 help="Run the trials as Ray tasks on an existing Ray cluster: auto (the cluster this machine is "
                      "part of, or RAY_ADDRESS) or the head's HOST:PORT. Needs the ray extra."),
]
SamplesOpt = Annotated[int, typer.Option("--samples", min=16, max=1 << 20, help="MPPI samples per step.")]
DistanceOpt = Annotated[
    float | None, typer.Option("--distance", min=1.0, max=1e5, help="Lane distance in m (100; lanes only).")
]
LatencyOpt = Annotated[float, typer.Option("--latency", min=0.0, max=10.0, help="Command latency in seconds.")]
LatencyCyclesOpt = Annotated[
    int, typer.Option("--latency-cycles", min=0, max=100, help="Latency in planner cycles.")
]
CompensateOpt = Annotated[
    bool, typer.Option("--compensate/--no-compensate", help="Planners plan for the state their command meets.")
]
NoiseOpt = Annotated[bool, typer.Option("--noise/--no-noise", help="Physics plant sensor noise.")]
DeployOpt = Annotated[
    Path | None,
    typer.Option("--launch-file", help="Launch file whose egress limits and terrain cycle (command_source, dt gating, "
                 "estimator) the closed loop runs (default: the default launch)."),
]
RandomOpt = Annotated[bool, typer.Option("--random-scenes", help="Avoidance: a random scene per trial.")]
SetOpt = Annotated[
    list[str] | None,
    typer.Option("--set", help="Planner setting for every model, KEY=VALUE (a PlannerConfig field; repeat)."),
]
EstimatorOpt = Annotated[
    list[str] | None,
    typer.Option("--estimator", help="Terrain estimator setting, KEY=VALUE (an EstimatorConfig field, e.g. "
                 "method=bayes; repeat)."),
]
OracleOpt = Annotated[
    bool, typer.Option("--oracle-weights", help="GP-MPPI gets the true terrain's weights instead of estimating them.")
]
SwitchOpt = Annotated[
    list[str] | None, typer.Option("--switch", help="Switch the plant's terrain mid-run: TIME:TERRAIN (repeat).")
]


def parse_switches(items: list[str] | None) -> tuple[tuple[float, str], ...]:
    out = []
    for item in items or []:
        t, _, name = item.partition(":")
        try:
            out.append((float(t), name))
        except ValueError:
            fail(f"--switch {item!r}: expected TIME:TERRAIN, e.g. 20:sand")
        if not name:
            fail(f"--switch {item!r}: missing terrain name")
    return tuple(out)


def parse_overrides(items: list[str] | None) -> tuple[tuple[str, object], ...]:
    import yaml
    from pydantic import ValidationError

    from gpmppi.mppi.planner import PlannerConfig

    out: dict[str, object] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or key not in PlannerConfig.model_fields or key in ("dynamics", "seed", "edd5_terrain"):
            fail(f"--set {item!r}: expected KEY=VALUE, KEY a planner setting (not dynamics, seed, edd5_terrain)")
        parsed = yaml.safe_load(value)
        out[key] = tuple(parsed) if isinstance(parsed, list) else parsed
    try:
        PlannerConfig(**out)
    except ValidationError as e:
        fail(f"--set: {e.errors()[0]['loc']}: {e.errors()[0]['msg']}")
    return tuple(out.items())
