"""Shared fixtures: where the paper's Jackal data lives (tests using it skip where it is absent)."""

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
