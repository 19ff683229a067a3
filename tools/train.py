"""`gpmppi train DATA -o PROFILE`: fit a robot profile from an MCAP log (the per-terrain residual GPs, the nominal
model, EDD5, lateral slip and the terrain estimator's calibration), or the GPs alone from a residual CSV."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from gpmppi.gp.coverage import (
    HOLD_S,
    MIN_COVERED,
    MIN_PER_CELL,
    MIN_SAMPLES,
    GroundCoverage,
    ground_coverage,
)
from gpmppi.gp.grid_table import DEFAULT_SPACING
from schemas.keys import DEFAULT_ROBOT
from tools.choices import FitMode
from tools.cli_checks import OUT_FILE, fail
from tools.train_data import DataError, csv_inputs, csv_residuals, is_mcap, read_csv_columns, read_logs_series

if TYPE_CHECKING:
    from gpmppi.gp.model_file import GPModel


def _load_json(path: Path | None, what: str) -> dict | None:
    if path is None:
        return None
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise DataError(f"{path}: no such {what} file") from None
    except json.JSONDecodeError as e:
        raise DataError(f"{path}: {what} file is not valid JSON ({e})") from None


def _edd5_from_json(data: dict, terrains: list[str], path: Path) -> dict[str, np.ndarray]:
    lower = {str(k).lower(): v for k, v in data.items()}
    missing = [t for t in terrains if t not in lower]
    if missing:
        raise DataError(f"{path}: no EDD5 parameters for terrains {missing} (file has {sorted(data)})")
    out = {}
    for t in terrains:
        p = np.asarray(lower[t], dtype=np.float64)
        if p.shape != (5,) or not np.all(np.isfinite(p)):
            raise DataError(f"{path}: EDD5 parameters for {t!r} must be 5 finite numbers")
        out[t] = p
    return out


def _theta_from_json(data: dict, path: Path) -> np.ndarray:
    theta = np.asarray(data.get("theta", data) if isinstance(data, dict) else data, dtype=np.float64)
    if theta.shape != (6,) or not np.all(np.isfinite(theta)) or np.any(theta[:2] <= 0):
        raise DataError(f"{path}: theta must be 6 finite numbers with theta1, theta2 > 0 (layout of theta.json)")
    return theta


def _select(available: list[str], wanted: list[str] | None, where: str) -> list[str]:
    """The wanted terrains (matched case-insensitively, in the data's spelling), or all available."""
    if not wanted:
        return available
    by_lower = {a.lower(): a for a in available}
    unknown = [t for t in wanted if t.lower() not in by_lower]
    if unknown:
        raise DataError(f"{where}: unknown terrain(s) {unknown}; the data has {available}")
    return [by_lower[t.lower()] for t in wanted]


def build_training_sets(
    data: Path | list[Path], terrain: list[str] | None, theta_path: Path | None, edd5_path: Path | None,
    dt: float, robot: str | None, seed: int,
) -> tuple[dict, np.ndarray, dict[str, np.ndarray], dict[str, int | None], dict[str, list] | None]:
    """(terrain -> Transitions, theta, EDD5 per terrain, held commands per terrain, terrain -> logged runs) from a
    CSV or from one or more MCAP logs (a CSV has no time series: its held commands and runs are None)."""
    paths = [data] if isinstance(data, Path) else list(data)
    if len(paths) > 1 and any(p.suffix.lower() == ".csv" for p in paths):
        raise DataError(f"give one residual CSV, or one or more MCAP logs, not both or several CSVs: "
                        f"{[str(p) for p in paths]}")
    data = paths[0]
    from gpmppi.gp.coverage import held_commands
    from gpmppi.gp.train import Transitions, prepare_from_series
    from gpmppi.models.dynamic_unicycle import velocity_step_exact
    from gpmppi.models.identify import identify_edd5
    from tools.profile_fit import runs_from_series

    theta_json, edd5_json = _load_json(theta_path, "theta"), _load_json(edd5_path, "EDD5")
    if data.suffix.lower() == ".csv":
        cols = read_csv_columns(data)
        x = csv_inputs(cols, data)
        res = csv_residuals(cols, data)
        terrains = _select(list(res), terrain, str(data))
        if theta_json is None:
            raise DataError(
                f"{data}: a residual CSV holds residuals of an unknown nominal model, so theta cannot be "
                "identified from it; pass --theta THETA.json"
            )
        theta = _theta_from_json(theta_json, theta_path)
        pv, pw = velocity_step_exact(theta, x[:, 2].copy(), x[:, 3].copy(), x[:, 0].copy(), x[:, 1].copy(), dt)
        sets = {t: Transitions(x, res[t], np.column_stack([pv, pw]) + res[t]) for t in terrains}
        if edd5_json is not None:
            edd5 = _edd5_from_json(edd5_json, terrains, edd5_path)
        else:  # EDD5 maps a command to the velocity it settles at: fit to the measured next velocities
            edd5 = {t: identify_edd5(x[:, 0], x[:, 1], s.next_vw[:, 0], s.next_vw[:, 1], seed=seed)
                    for t, s in sets.items()}
        return sets, theta, edd5, dict.fromkeys(terrains), None
    for path in paths:
        if not is_mcap(path):
            raise DataError(f"{path}: not an MCAP file (nor a .csv); give logs recorded by `gpmppi calibrate drive`, "
                            "`gpmppi launch --record` or `gpmppi dataset`, or a residual CSV")
    series = read_logs_series(paths, dt, terrain[0] if terrain and len(terrain) == 1 else None, robot)
    terrains = _select(sorted(series), terrain, ", ".join(str(p) for p in paths))
    th = _theta_from_json(theta_json, theta_path) if theta_json is not None else None
    ed = _edd5_from_json(edd5_json, terrains, edd5_path) if edd5_json is not None else None
    held = {t: held_commands(np.asarray(series[t]["v_ref"]), np.asarray(series[t]["w_ref"]),
                             np.asarray(series[t]["seg"]), dt) for t in terrains}
    chosen = {t: series[t] for t in terrains}
    return (*prepare_from_series(chosen, dt, theta=th, edd5=ed, seed=seed), held, runs_from_series(chosen, dt))


def print_coverage(coverage: list[GroundCoverage], console: Console) -> None:
    """Per ground: the share of the planner's command and state range its data covers, its held commands, and a
    warning naming the thin command cells."""
    table = Table(title="coverage of the planner's range (v 0-2 m/s, |omega| up to pi rad/s; a cell counts from "
                        f"{MIN_PER_CELL} samples)")
    for col in ("terrain", "samples", "commands covered", "states covered", f"held commands (>= {HOLD_S:g} s)"):
        table.add_column(col, justify="right")
    for c in coverage:
        table.add_row(c.terrain, str(c.samples), f"{c.command_covered:.0%}", f"{c.state_covered:.0%}",
                      "-" if c.held is None else str(c.held))
    console.print(table)
    for c in coverage:
        thin = c.thin()
        if thin:
            Console(stderr=True, soft_wrap=True).print(
                f"[yellow]warning:[/yellow] ground {c.terrain!r}: thin coverage in {len(thin)} of "
                f"{c.command_cells.size} command cells, the GP extrapolates there; drive: {'; '.join(thin[:4])}"
                + (" ..." if len(thin) > 4 else ""), highlight=False)


def print_report(report, console: Console) -> None:
    table = Table(title=f"GP fit: one-step RMSE on {report.eval_set}")
    for col in ("terrain", "output", "steps", "RMSE nominal", "RMSE nominal+GP", "NLL"):
        table.add_column(col, justify="right")
    for f in report.terrains:
        for o, name in enumerate(("v", "omega")):
            table.add_row(f.terrain, name, str(f.n_eval), f"{f.rmse_nominal[o]:.4f}", f"{f.rmse_gp[o]:.4f}",
                          f"{f.nll[o]:.3f}")
    console.print(table)
    if report.clipped:
        console.print(f"{report.clipped} training targets clipped as outliers (beyond 5 robust standard deviations)")
    if not report.held_out:
        console.print("no held-out data: these are training-set figures and cannot show overfitting "
                      "(use --holdout or --test-data)")
    if report.final_loss is not None:
        console.print(f"negative log posterior per point of the chosen fit (targets scaled to unit RMS): "
                      f"{report.final_loss:.4f}")


def _test_sets(test_data: Path, sets: dict, terrain: list[str] | None) -> dict:
    """`--test-data`: a residual CSV's transitions per trained terrain; a DataError where its terrains differ."""
    from gpmppi.gp.train import Transitions

    cols = read_csv_columns(test_data)
    tx, tres = csv_inputs(cols, test_data), csv_residuals(cols, test_data)
    missing = [t for t in sets if t not in tres]
    extra = [] if terrain else sorted(t for t in tres if t not in sets)
    if missing or extra:
        raise DataError(
            f"{test_data}: its terrains {sorted(tres)} differ from the training data's {sorted(sets)}: "
            + (f"no residual columns for {missing}" if missing else "")
            + ("; " if missing and extra else "")
            + (f"terrains {extra} were not trained (pass --terrain to choose those to train and test)"
               if extra else "")
        )
    return {t: Transitions(tx, tres[t]) for t in sets}


def _print_profile(model: GPModel, report, coverage: list[GroundCoverage], output: Path,  # noqa: ANN001
                   console: Console) -> None:
    """What `gpmppi train` wrote: the fit, the coverage, its warnings, the profile's parts."""
    print_report(report, console)
    print_coverage(coverage, console)
    for line in model.fit_warnings():
        Console(stderr=True, soft_wrap=True).print(f"[yellow]warning:[/yellow] {line}", highlight=False)
    console.print(
        f"wrote {output}: terrains {model.terrains}, {len(model.train_x)} training inputs, "
        f"theta {np.array2string(model.theta, precision=4)}"
    )
    lateral = ", ".join(f"{t} ({p[0]:+.4f}, {p[1]:+.4f})" for t, p in model.lateral_slip.items())
    console.print(f"lateral slip (a, b) of v_y = (a + b |omega|) v omega: {lateral}")
    if model.calibration is None:
        Console(stderr=True, soft_wrap=True).print(
            "[yellow]warning:[/yellow] no terrain calibration: the data has no time series (a residual CSV); the "
            "terrain estimator needs command_change: online and response: none with this file", highlight=False)
    else:
        gains = ", ".join(f"{t} ({g[0]:+.3f}, {g[1]:+.3f})"
                          for t, g in zip(model.terrains, model.calibration.command_gain, strict=True))
        console.print(f"robot profile of {model.robot!r}: terrain calibration of {list(model.terrains)}; "
                      f"command-change gains (v, omega): {gains}")
        logs = (model.fit_report or {}).get("logs", {})
        if logs.get("calibration_only"):
            holds = ", ".join(f"{t} {n} ({logs['calibration_only_holds'][t]} from them)"
                              for t, n in logs["calibration_holds"].items())
            console.print(f"terrain calibration from the training logs and {len(logs['calibration_only'])} "
                          f"calibration-only log(s) (not in the GP's data); settled held commands: {holds}")
    if model.novelty is not None:
        n = model.novelty
        console.print(f"novelty test: P(unknown ground) = 0.5 at {n.enter:.2f} spreads of the windowed mean "
                      f"residual (spread v {n.spread[0]:.4f} m/s, omega {n.spread[1]:.4f} rad/s, "
                      f"{n.window_steps} steps)")
        if n.free_run is not None:
            f = n.free_run
            console.print(f"novelty test, free-run channel: P(unknown ground) = 0.5 at {f.enter:.2f} spreads of the "
                          f"windowed mean {f.horizon_steps}-step free-run error (spread v {f.spread[0]:.4f} m/s, "
                          f"omega {f.spread[1]:.4f} rad/s, {f.window_steps} steps)")


def register(app: typer.Typer) -> None:
    """Add `gpmppi train`."""

    @app.command("train")
    def train_cmd(
        data: Annotated[list[Path], typer.Argument(
            help="MCAP logs (state, cmd, terrain labels; one or more, e.g. one per ground and run) or one residual "
                 "CSV")],
        output: Annotated[Path, typer.Option("--output", "-o", metavar=OUT_FILE,
                                             help="robot profile to write (.npz)")],
        terrain: Annotated[list[str] | None, typer.Option(
            "--terrain", "-t", help="terrain name of an unlabeled log; or, repeated, the terrains to keep")] = None,
        hyperparameters: Annotated[Path | None, typer.Option(
            help="fixed hyperparameters (layout of gp_hyperparameters.json) instead of fitting")] = None,
        theta: Annotated[Path | None, typer.Option(help="nominal parameters JSON (layout of theta.json)")] = None,
        edd5: Annotated[Path | None, typer.Option(help="EDD5 parameters per terrain JSON (edd5.json layout)")] = None,
        test_data: Annotated[Path | None, typer.Option(help="residual CSV to report the fit on")] = None,
        holdout: Annotated[float | None, typer.Option(
            min=0.0, help="fraction held out of training for the fit report and its warnings "
                 "(default: 0.2; 0 with --test-data, which is then the held-out set, and with --hyperparameters)")
        ] = None,
        points: Annotated[int, typer.Option(min=1, help="number of shared GP training inputs")] = 300,
        steady_points: Annotated[int, typer.Option(
            min=0, help="of the --points inputs, this many at rows whose command was held 2 s or more (k-means of "
                        "those rows; targets their local mean): the GP's steady states (0: inputs chosen over all "
                        "rows alike)")] = 0,
        iters: Annotated[int, typer.Option(min=0, help="Adam iterations of the hyperparameter fit")] = 200,
        fit: Annotated[FitMode, typer.Option(
            "--fit", help="stable: the GP's inputs (k-means) and the restarts started alike whatever --seed, each "
                          "task's hyperparameters chosen among the restarts' steps by leave-one-out on all the inputs "
                          "(--seed draws only the held-out split); seeded: all of these drawn by --seed, the choice on "
                          "one validation fold (the earlier fit, which made the shipped profile)")] = FitMode.seeded,
        seed: Annotated[int, typer.Option(min=0, help="seed of k-means, the holdout split and the fit")] = 0,
        dt: Annotated[float, typer.Option(min=0.001, max=10.0, help="sampling step of the data [s]")] = 0.1,
        robot: Annotated[str, typer.Option(
            help="the robot: its name in the log keys gpmppi/{robot}/..., stored in the profile")] = DEFAULT_ROBOT,
        grid_nodes: Annotated[int | None, typer.Option(
            min=0, max=200,
            help="grid predictor nodes on every axis of the stored table (0: store none, build on first use; "
                 "default: each axis sized from its smallest lengthscale, see --grid-spacing)")] = None,
        grid_spacing: Annotated[float, typer.Option(
            min=0.001, max=10.0,
            help="node spacing of the stored grid table as a fraction of each axis's smallest lengthscale")
        ] = DEFAULT_SPACING,
        min_samples: Annotated[int, typer.Option(
            min=1, help="refuse a ground with fewer one-step samples")] = MIN_SAMPLES,
        min_coverage: Annotated[float, typer.Option(
            min=0.0, max=1.0, help="refuse a ground whose commands cover a smaller share of the planner's range "
                                   f"(cells with {MIN_PER_CELL} samples or more)")] = MIN_COVERED,
        calibration_log: Annotated[list[Path] | None, typer.Option(
            "--calibration-log",
            help="MCAP log for the terrain estimator's calibration only (steady map, command-change gains, rate), "
                 "never the GP's or the nominal model's training data; e.g. a drive with lane holds (`gpmppi dataset "
                 "--lane-holds`); repeat for several")] = None,
        force: Annotated[bool, typer.Option("--force", help="replace an existing --output file")] = False,
    ) -> None:
        """Fit a robot profile from a log: the per-terrain residual GPs and the terrain calibration."""
        from gpmppi.gp.grid_table import build_grid
        from gpmppi.gp.train import train_model
        from gpmppi.terrain.log_calibration import (
            calibrate_from_runs,
            calibration_holds,
            novelty_from_runs,
            settled_holds,
        )
        from tools.profile_fit import calibration_log_runs, check_calibration_data, train_command

        console = Console()
        try:
            if not 0.0 <= (holdout or 0.0) < 1.0:
                raise DataError(f"--holdout must be in [0, 1), got {holdout}")
            check_calibration_data(calibration_log or [], data)
            sets, th, ed, held, runs = build_training_sets(data, terrain, theta, edd5, dt, robot, seed)
            if steady_points and runs is None:
                raise DataError("--steady-points needs logs with time series (how long each command was held); a "
                                "residual CSV has none")
            calibration_only = calibration_log_runs(calibration_log or [], data, list(sets), terrain, dt, robot)
            # the calibration's data: the training logs' runs, then the calibration logs' (the GP never sees these)
            calibration_runs = None if runs is None else {
                t: runs.get(t, []) + calibration_only.get(t, []) for t in sets}
            test_sets = None if test_data is None else _test_sets(test_data, sets, terrain)
            coverage = [ground_coverage(t, s.x, held[t]) for t, s in sets.items()]
            refused = [r for c in coverage if (r := c.problem(min_samples, min_coverage)) is not None]
            if refused:
                raise DataError("; ".join(refused))
            if calibration_runs is not None:  # before the GP's fit: a log that cannot calibrate is refused at once
                holds = calibration_holds(calibration_runs, list(sets))
            # given hyperparameters (the paper's procedure) condition on all the data, as the paper did
            hold = holdout if holdout is not None else (0.0 if test_sets is not None or hyperparameters else 0.2)
            model, report = train_model(
                sets, th, ed, dt=dt, points=points, iters=iters, seed=seed,
                hyperparameters=_load_json(hyperparameters, "hyperparameter"), holdout=hold, test_sets=test_sets,
                steady_points=steady_points, fit=fit.value,
            )
            if grid_nodes is not None and (grid_nodes == 1 or grid_nodes < 0):
                raise DataError(f"--grid-nodes must be 0 (no stored grid) or at least 2, got {grid_nodes}")
            if not grid_spacing > 0:
                raise DataError(f"--grid-spacing must be positive, got {grid_spacing}")
            if grid_nodes != 0:
                model.set_grid(build_grid(model, grid_nodes, spacing=grid_spacing))
            model.robot = robot
            model.fit_report = {**(model.fit_report or {}), "coverage": [  # what the drive reached, per ground
                {"terrain": c.terrain, "samples": c.samples, "commands_covered": c.command_covered,
                 "states_covered": c.state_covered, "held_commands": c.held} for c in coverage]}
            model.made_by = train_command([str(p) for p in data], str(output), robot, terrain, points, iters, seed,
                                          holdout, [str(p) for p in calibration_log or []], steady_points,
                                          fit.value)
            if calibration_runs is not None:
                model.fit_report["logs"] = {  # which logs fed what
                    "training": [str(p) for p in data], "calibration_only": [str(p) for p in calibration_log or []],
                    "calibration_holds": {t: len(h) for t, h in holds.items()},
                    "calibration_only_holds": {t: sum(len(settled_holds(r)) for r in calibration_only.get(t, []))
                                               for t in holds}}
                model.calibration = calibrate_from_runs(model, calibration_runs)
                try:
                    model.novelty = novelty_from_runs(model, calibration_runs)
                except ValueError as e:  # too short to calibrate: the profile works with the test's stated default
                    Console(stderr=True, soft_wrap=True).print(f"[yellow]warning:[/yellow] {e}; the profile's novelty "
                                                               "test uses its stated default", highlight=False)
        except ValueError as e:
            fail(str(e))
        model.save(output)
        _print_profile(model, report, coverage, output, console)
