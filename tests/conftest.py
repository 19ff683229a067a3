"""Shared fixtures: where the paper's Jackal data lives (tests using it skip where it is absent), and the model
`gpmppi train` makes from it (trained once per session for the modules that compare it with GPyTorch)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def jackal_dir() -> Path:
    return Path(os.environ.get("GPMPPI_JACKAL_DATA", REPO.parent / "shared" / "jackal-paper"))


@pytest.fixture(scope="session")
def jackal() -> Path:
    d = jackal_dir()
    if not (d / "gp_train.csv").is_file():
        pytest.skip(f"paper data not found at {d} (set GPMPPI_JACKAL_DATA)")
    return d


@pytest.fixture(scope="session")
def paper_model_file(jackal: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The paper's fitted GP as `gpmppi train` writes it (with the grid table it stores by default): the same
    command for every module that uses it, so it is trained once (~10-17 s); the tests only read the file."""
    from typer.testing import CliRunner

    from tools.cli import app

    out = tmp_path_factory.mktemp("paper") / "m.npz"
    result = CliRunner().invoke(app, [
        "train", str(jackal / "gp_train.csv"), "--hyperparameters", str(jackal / "gp_hyperparameters.json"),
        "--theta", str(jackal / "theta.json"), "--edd5", str(jackal / "edd5.json"), "-o", str(out),
    ])
    assert result.exit_code == 0, result.output
    return out
