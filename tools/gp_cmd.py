"""`gpmppi gp ...`: use a trained GP model (predict at given inputs)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import typer
from rich.console import Console

from tools.cli_checks import OUT_FILE, AtomicOutput, fail
from tools.train_data import INPUT_COLUMNS, DataError, csv_inputs, read_csv_columns


def write_csv_atomic(path: Path, header: list[str], rows: np.ndarray) -> None:
    """Write a numeric CSV via a temp file in the same folder, then rename (no half-written output)."""
    with AtomicOutput(path) as tmp, tmp.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        for r in rows:
            w.writerow([repr(float(v)) for v in r])


def register(app: typer.Typer) -> None:
    """Add `gpmppi gp predict`."""
    gp_app = typer.Typer(help="Use a trained GP model.", no_args_is_help=True)

    @gp_app.command("predict")
    def predict_cmd(
        inputs: Annotated[Path, typer.Argument(help=f"CSV with columns {','.join(INPUT_COLUMNS)} (or gp_ip_*)")],
        model_path: Annotated[Path, typer.Option("--profile", help="robot profile from `gpmppi train`")],
        output: Annotated[Path, typer.Option("--output", "-o", metavar=OUT_FILE, help="CSV to write")],
        mode: Annotated[str, typer.Option(help="exact | grid")] = "exact",
        force: Annotated[bool, typer.Option("--force", help="replace an existing --output file")] = False,
    ) -> None:
        """Predict each task's mean and latent variance (no noise) at the inputs."""
        from gpmppi.gp.exact import ExactPredictor
        from gpmppi.gp.grid import GridPredictor
        from gpmppi.gp.model_file import GPModel

        try:
            if mode not in ("exact", "grid"):
                raise DataError(f"--mode must be 'exact' or 'grid', got {mode!r}")
            m: Literal["exact", "grid"] = mode  # type: ignore[assignment]
            model = GPModel.load(model_path)
            x = csv_inputs(read_csv_columns(inputs), inputs)
        except ValueError as e:
            fail(str(e))
        predictor = ExactPredictor(model) if m == "exact" else GridPredictor(model)
        mean, var = predictor.predict(x)
        header = list(INPUT_COLUMNS)
        cols = [x]
        for t, name in enumerate(model.tasks):
            header += [f"{name}_mean", f"{name}_var"]
            cols += [mean[:, t : t + 1], var[:, t : t + 1]]
        write_csv_atomic(output, header, np.hstack(cols))
        Console().print(f"wrote {output}: {len(x)} rows, {model.n_tasks} tasks ({m})")

    app.add_typer(gp_app, name="gp")
