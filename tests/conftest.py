"""Shared fixtures: where the paper's Jackal data lives (tests using it skip where it is absent), and the model
`gpmppi train` makes from it (trained once per session for the modules that compare it with GPyTorch); the
`exclusive` tests run alone while the others run on several workers."""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from collections.abc import Iterator
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


# ------------------------------------------------------------------------------------- tests that run alone
# The suite runs on several workers (pytest-xdist, `addopts` in pyproject.toml). A few tests compare wall-clock
# times (the egress watchdog within 20 ms of its deadline, a stopped viewer against a running one, a soak's
# latencies, faults injected into a running stack), and a second worker's test beside them would be load they
# would measure. Those are marked `exclusive`: each runs alone. A readers-writer lock over files shared by the
# run's workers: every test holds the lock shared, an exclusive one holds it alone; the turnstile makes the
# other workers' next tests wait behind an exclusive one that waits for the lock (else they could keep it
# shared for ever).


@contextlib.contextmanager
def _run_lock(exclusive: bool) -> Iterator[None]:
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if run is None:  # one process runs the tests: nothing runs beside them
        yield
        return
    base = Path(tempfile.gettempdir()) / f"gpmppi-tests-{run}"
    with open(f"{base}.turnstile", "a") as turnstile, open(f"{base}.lock", "a") as lock:
        fcntl.flock(turnstile, fcntl.LOCK_EX)
        if exclusive:
            fcntl.flock(lock, fcntl.LOCK_EX)  # the tests running now end; those after wait at the turnstile
            fcntl.flock(turnstile, fcntl.LOCK_UN)
        else:
            fcntl.flock(turnstile, fcntl.LOCK_UN)
            fcntl.flock(lock, fcntl.LOCK_SH)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """Setup, call and teardown of each test under the run's lock (alone for the `exclusive` tests)."""
    with _run_lock(item.get_closest_marker("exclusive") is not None):
        yield

