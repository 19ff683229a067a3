"""`gpmppi evaluate terrain-gains`, `terrain-response`, `terrain-log-calibration`: the CLI over the terrain
estimator's calibration (`gpmppi.terrain.calibration`, `gpmppi.terrain.log_calibration`), and the estimator settings
given as KEY=VALUE items that the evaluation's commands share (`estimator_settings`). `terrain-separability` is
`tools.terrain_separability`.
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
import yaml

from tools.cli_checks import OUT_FILE, write_text_atomic


def estimator_settings(items: list[str]) -> tuple[tuple[str, object], ...]:
    """KEY=VALUE items (EstimatorConfig fields) -> validated ((key, value), ...); ValueError naming what is wrong."""
    from pydantic import ValidationError

    from gpmppi.terrain.settings import EstimatorConfig

    out: dict[str, object] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"{item!r}: expected KEY=VALUE (e.g. method=bayes)")
        if key not in EstimatorConfig.model_fields:
            raise ValueError(f"{item!r}: no estimator setting {key!r}; the settings are "
                             f"{', '.join(sorted(EstimatorConfig.model_fields))}")
        parsed = yaml.safe_load(value)
        out[key] = tuple(parsed) if isinstance(parsed, list) else parsed
    try:
        EstimatorConfig(**out)
    except ValidationError as e:
        err = e.errors()[0]
        raise ValueError(f"{'.'.join(str(x) for x in err['loc']) or 'settings'}: {err['msg']}") from None
    return tuple(out.items())


def written_by() -> str:
    """The command line that wrote a file, for its header."""
    return "gpmppi " + " ".join(shlex.quote(a) for a in sys.argv[1:])


def gains_cmd(
    distance: Annotated[float, typer.Option(
        "--distance", min=10.0, max=1e5, help="Excitation distance per terrain in m.")] = 400.0,
    seed: Annotated[int, typer.Option("--seed", min=0, help="Excitation and plant seed.")] = 5,
    out: Annotated[Path | None, typer.Option("--output", "-o", metavar=OUT_FILE, help="Write the YAML here.")
                   ] = None,
) -> None:
    """Fit the terrain estimator's per-terrain command-change gains on excitation drives of the physics plant.

    Drives each terrain of the GP model with the training data's excitation commands (not a controller), and
    fits per output the least-squares gain of that terrain's GP residual on the change of command since the
    previous step (`gpmppi.terrain.calibration.fit_command_gain`).
    """
    from gpmppi.evaluation.runner import cached_gp_model, cached_terrain_set
    from gpmppi.plant.physics import PhysicsPlant
    from gpmppi.terrain.calibration import command_gains_yaml, fit_command_gains

    model = cached_gp_model(None)
    gains = fit_command_gains(model, lambda t: PhysicsPlant(cached_terrain_set(None), t, seed=seed), distance, seed)
    text = command_gains_yaml(gains, written_by())
    if out is not None:
        write_text_atomic(out, text)
    print(text, end="")


def response_cmd(
    settle: Annotated[float, typer.Option(
        "--settle", min=0.5, max=60.0, help="Seconds each held command runs before its velocities are averaged.")
    ] = 2.5,
    average: Annotated[float, typer.Option(
        "--average", min=0.1, max=60.0, help="Seconds of measured velocity averaged per held command.")] = 1.5,
    distance: Annotated[float, typer.Option(
        "--distance", min=10.0, max=1e5, help="Excitation distance per terrain in m (for the rates).")] = 400.0,
    seed: Annotated[int, typer.Option("--seed", min=0, help="Excitation and plant seed.")] = 5,
    plant: Annotated[str, typer.Option("--plant", help="physics (default) or residual-net (the paper's "
                                       "simulator, with --plant-file).")] = "physics",
    plant_file: Annotated[Path | None, typer.Option("--plant-file", help="Residual-net JSON (the paper's "
                                                    "fcnn.json).")] = None,
    gp_model: Annotated[Path | None, typer.Option("--profile", help="Robot profile whose terrains to fit (and, "
                                                  "for residual-net, whose nominal model).")] = None,
    out: Annotated[Path | None, typer.Option("--output", "-o", metavar=OUT_FILE, help="Write the YAML here.")
                   ] = None,
) -> None:
    """Fit each terrain's velocity response (gpmppi.profile.response) on drives of the plant.

    Per terrain of the GP model (--profile; default the shipped one) on --plant: holds every command of a
    (v_ref, omega_ref) grid from rest for --settle s and
    averages the measured (sensor-noisy) velocities over the next --average s (the steady map); then fits the
    one-step rate of approach to it on the training data's excitation commands. On a robot, the same drives:
    hold each command, log the settled velocities.
    """
    from gpmppi.evaluation.runner import EvalSettings, cached_gp_model, make_plant
    from gpmppi.terrain.calibration import fit_response, response_yaml

    if plant not in ("physics", "residual-net"):
        raise typer.BadParameter(f"--plant must be physics or residual-net, got {plant!r}")
    settings = EvalSettings(plant=plant, plant_file=None if plant_file is None else str(plant_file),  # type: ignore[arg-type]
                            gp_model=None if gp_model is None else str(gp_model))
    names = list(cached_gp_model(settings.gp_model).terrains)
    response = fit_response(names, lambda t: make_plant(settings, t, seed), settle, average, distance, seed)
    text = response_yaml(response, written_by())
    if out is not None:
        write_text_atomic(out, text)
    print(text if out is None else f"wrote {out}: terrains {names}, rates {np.round(response.rate, 3).tolist()}")


def log_calibration_cmd(
    data: Annotated[Path, typer.Argument(help="MCAP log with state, cmd and terrain labels (`gpmppi dataset` or a "
                                         "robot's log).")],
    gp_model: Annotated[Path | None, typer.Option(
        "--profile", help="Robot profile (its GP) trained on that log (default: the shipped one).")] = None,
    gains_out: Annotated[Path | None, typer.Option("--gains-output", metavar=OUT_FILE, help="Write the gains YAML "
                                                   "here.")] = None,
    response_out: Annotated[Path | None, typer.Option("--response-output", metavar=OUT_FILE, help="Write the "
                                                      "response YAML here.")] = None,
    robot: Annotated[str, typer.Option("--robot", help="Robot name in the log's keys.")] = "jackal",
) -> None:
    """Fit the terrain estimator's calibration (command-change gains, steady response) from a log alone.

    The log's held commands give each ground's steady map, every step its rate and gains
    (`gpmppi.terrain.log_calibration`). Prints the `--estimator` settings that use them.
    """
    from gpmppi.evaluation.runner import cached_gp_model
    from gpmppi.terrain.calibration import command_gains_yaml, response_yaml
    from gpmppi.terrain.log_calibration import calibrate_from_runs
    from tools.cli_checks import fail
    from tools.dataset import read_dataset

    try:
        runs = read_dataset(data, robot=robot)
    except (ValueError, FileNotFoundError) as e:
        fail(str(e))
    cal = calibrate_from_runs(cached_gp_model(None if gp_model is None else str(gp_model)), runs)
    gains = {t: cal.command_gain[i] for i, t in enumerate(cal.terrains)}
    if gains_out is not None:
        write_text_atomic(gains_out, command_gains_yaml(gains, written_by()))
    if response_out is not None:
        write_text_atomic(response_out, response_yaml(cal.response, written_by()))
    inline = ", ".join(f"{t}: [{g[0]:.4f}, {g[1]:.4f}]" for t, g in gains.items())
    print(f"--estimator 'command_gains={{{inline}}}'"
          + (f" --estimator response_file={response_out}" if response_out is not None else ""))
    for i, t in enumerate(cal.terrains):
        rate, gain = np.round(cal.response.rate[i], 3).tolist(), np.round(cal.command_gain[i], 4).tolist()
        print(f"{t}: rate {rate}, gain {gain}")


def register(ev: typer.Typer) -> None:
    """Add `gpmppi evaluate terrain-gains`, `terrain-response` and `terrain-log-calibration` to the evaluate
    group."""
    ev.command("terrain-gains")(gains_cmd)
    ev.command("terrain-response")(response_cmd)
    ev.command("terrain-log-calibration")(log_calibration_cmd)


