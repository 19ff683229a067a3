"""Shared fixtures: where the paper's Jackal data lives (tests using it skip where it is absent), and the model
`gpmppi train` makes from it (trained once per session for the modules that compare it with GPyTorch); the
`exclusive` tests ahead of the others for the CPU (or alone) while the others run on several workers; each test's
CPU seconds where asked (`GPMPPI_TEST_CPU_LOG`)."""

from __future__ import annotations

import contextlib
import fcntl
import gc
import os
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
import threadpoolctl

# Python's byte-code cache on, for this run and every process it starts: where the environment sets
# PYTHONDONTWRITEBYTECODE (some images do), no .pyc is written, and each of the suite's hundreds of processes (its
# workers, the services a test starts, the compiles in processes of their own) compiled every module it imported
# from source, numpy's and torch's too (deploy/setup.sh installs with --no-compile): `pytest -m "not slow"` from a
# fresh clone took 215 s with it set, 131 s with it unset and 118 s once the cache was written (docs/development.md).
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
sys.dont_write_bytecode = False

# The cyclic garbage collector less often in the test processes (not in the services they start): a worker holds
# ~500,000 objects once torch, numba and the services' modules are imported, and each full collection walks them all;
# at Python's default (700, 10, 10) the collector took 3.3 of 41 CPU seconds of tests/test_robot_profile.py with
# tests/test_train_calibration_log.py (-n 0; 2891 collections), 1.1 s at these thresholds (59 collections).
# No test waits on a collection: every resource is closed where it is used.
gc.set_threshold(20_000, 20, 20)

# One BLAS thread in each test process and in every process it starts. numpy's and scipy's OpenBLAS start a thread per
# core for a large enough product or solve, and those threads spin while they wait for each other; with three workers
# and their services on two cores they mostly wait: under that load a 120 x 120 solve cost 4.7 ms of CPU with two
# threads against 0.09 ms with one, and `synthetic_model()` 0.62 against 0.09 CPU s (docs/development.md). The
# environment variable is read when a process loads OpenBLAS (the services, the CLI runs and the compiles in processes
# of their own); this process loaded it before this file (a pytest plugin imports numpy), so it is set here as well.
os.environ["OPENBLAS_NUM_THREADS"] = "1"
threadpoolctl.threadpool_limits(limits=1, user_api="blas")

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
    command for every module that uses it, so it is trained once a run (~10-17 s of CPU), not once a worker: the
    first worker to ask trains it into the run's shared temporary folder under a lock, the others wait for that
    lock and read the file; the tests only read it."""
    out = shared_folder(tmp_path_factory, "paper") / "m.npz"
    return once_a_run(tmp_path_factory, "paper", [
        "train", str(jackal / "gp_train.csv"), "--hyperparameters", str(jackal / "gp_hyperparameters.json"),
        "--theta", str(jackal / "theta.json"), "--edd5", str(jackal / "edd5.json"), "-o", str(out), "--force",
    ], out)


# the small two-ground log of the profile tests, and the profile `gpmppi train` fits on it with these settings (few
# points and iterations, no grid table: the file, not the fit's quality, is what those tests check)
PROFILE_GROUNDS = ["grass", "tile"]
FAST_TRAIN = ["--points", "30", "--iters", "10", "--grid-nodes", "0"]


@pytest.fixture(scope="session")
def grounds_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`gpmppi dataset` of 300 m on each of `PROFILE_GROUNDS` (seed 0), made once a run for every module that trains
    on it (tests/test_robot_profile.py, tests/test_train_calibration_log.py); the tests only read it."""
    out = shared_folder(tmp_path_factory, "grounds-log") / "ds.mcap"
    return once_a_run(tmp_path_factory, "grounds-log", [
        "dataset", "-o", str(out), "--distance", "300", "--seed", "0", *[a for g in PROFILE_GROUNDS for a in ("-t", g)],
    ], out)


@pytest.fixture(scope="session")
def grounds_profile(grounds_log: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The profile `gpmppi train LOG -o OUT --points 30 --iters 10 --grid-nodes 0` writes from `grounds_log`, trained
    once a run (~8 CPU s) for the tests that check it (tests/test_robot_profile.py) and compare another training with
    it (tests/test_train_calibration_log.py); the tests only read it."""
    out = shared_folder(tmp_path_factory, "grounds-profile") / "p.npz"
    return once_a_run(tmp_path_factory, "grounds-profile", ["train", str(grounds_log), "-o", str(out), *FAST_TRAIN],
                      out)


def once_a_run(tmp_path_factory: pytest.TempPathFactory, name: str, args: list[str], out: Path) -> Path:
    """`gpmppi ARGS` (which writes `out`, inside `shared_folder(.., name)`) once a run: the first worker to ask runs it
    under a lock, the others wait for that lock and find it done. A command that failed fails the test that asked,
    and the next one to ask runs it again."""
    from typer.testing import CliRunner

    from tools.cli import app

    folder = shared_folder(tmp_path_factory, name)
    with open(folder / "run.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # held while it runs: the other workers wait here, then find the file
        done = folder / "done"  # written after a run that succeeded
        if not done.is_file():
            result = CliRunner().invoke(app, args)
            assert result.exit_code == 0, result.output
            assert out.is_file(), f"gpmppi {' '.join(args)} wrote no {out}"
            done.touch()
    return out


def shared_folder(tmp_path_factory: pytest.TempPathFactory, name: str) -> Path:
    """A folder shared by every worker of this run (pytest-xdist's workers each have their own base temporary
    folder, `popen-gwN`, inside the run's one), or this process's own where one process runs the tests."""
    base = tmp_path_factory.getbasetemp()
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    # named by the run too: with `--basetemp` the run's folder is the same from run to run
    folder = base / f"shared-{name}" if run is None else base.parent / f"shared-{name}-{run}"
    folder.mkdir(exist_ok=True)
    return folder


# ------------------------------------------------------------------------------------------- how many workers
def pytest_xdist_auto_num_workers(config: pytest.Config) -> int | None:
    """`-n auto` (pyproject.toml's `addopts`): one worker more than the cores this process may run on.

    The suite waits about a third of its time (service processes starting, sockets, timed phases): on 2 cores two
    workers kept the CPU 62% busy in `-m "not slow"`, and three ran it in 116 s against 134 s, the whole suite in
    285-311 s against 340-359 s (docs/development.md). `PYTEST_XDIST_AUTO_NUM_WORKERS` still decides where set,
    and `--maxprocesses` caps either."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return None  # pytest-xdist's own hook reads it
    return len(os.sched_getaffinity(0)) + 1


# ------------------------------------------------------------------------------------- tests that run alone
# The suite runs on several workers (pytest-xdist, `addopts` in pyproject.toml). A few tests compare wall-clock
# times (the egress watchdog within 20 ms of its deadline, a stopped viewer against a running one, a soak's
# latencies, faults injected into a running stack), and a second worker's test beside them would be load they
# would measure. Those are marked `exclusive`.
#
# Where this process may raise its CPU priority (root or CAP_SYS_NICE; CI runs as root), an exclusive test runs
# beside the others with its worker's threads, and so the service processes it starts, at nice -20: the scheduler
# weighs each of its threads as 87 of the others' (88761 against 1024) and lets it preempt them on waking, so the
# others' load is not what it measures, and the cores it leaves idle are used (at -10, weight 9548, a replay's timer
# at a load of 8-12 was 3.8 ms late at the median, against 2 ms allowed). Alone, an exclusive test left the other
# core mostly idle: they took about 170 s of the suite's 720 s, using about one core. Exclusive tests never run
# beside each other (a lock of their own).
#
# Elsewhere, or with GPMPPI_TESTS_EXCLUSIVE_ALONE=1, each runs alone: a readers-writer lock over files shared by the
# run's workers, every test holds it shared, an exclusive one holds it alone; the turnstile makes the other workers'
# next tests wait behind an exclusive one that waits for the lock (else they could keep it shared for ever).
EXCLUSIVE_NICE = -20


def _set_nice(value: int) -> bool:
    """Every thread of this process (Linux keeps a niceness per thread; new threads and child processes inherit
    their creator's) at `value`; False, changing nothing, where not allowed."""
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return False
    for k, tid in enumerate(tids):
        try:
            os.setpriority(os.PRIO_PROCESS, tid, value)
        except ProcessLookupError:  # a thread that ended meanwhile
            continue
        except PermissionError:
            if k == 0:
                return False
            raise
    return True


@contextlib.contextmanager
def _run_lock(exclusive: bool) -> Iterator[None]:
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if run is None:  # one process runs the tests: nothing runs beside them
        yield
        return
    base = Path(tempfile.gettempdir()) / f"gpmppi-tests-{run}"
    own_nice = os.getpriority(os.PRIO_PROCESS, 0)
    ahead = (exclusive and os.environ.get("GPMPPI_TESTS_EXCLUSIVE_ALONE") != "1"
             and own_nice > EXCLUSIVE_NICE and _set_nice(EXCLUSIVE_NICE))
    with contextlib.ExitStack() as held:
        if ahead:
            one_at_a_time = held.enter_context(open(f"{base}.exclusive", "a"))
            fcntl.flock(one_at_a_time, fcntl.LOCK_EX)
            held.callback(_set_nice, own_nice)
        turnstile = held.enter_context(open(f"{base}.turnstile", "a"))
        lock = held.enter_context(open(f"{base}.lock", "a"))
        fcntl.flock(turnstile, fcntl.LOCK_EX)
        if exclusive and not ahead:
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
    with _run_lock(item.get_closest_marker("exclusive") is not None), _cpu_seconds(item):
        yield


@contextlib.contextmanager
def _cpu_seconds(item: pytest.Item) -> Iterator[None]:
    """With `GPMPPI_TEST_CPU_LOG` set: appends a line per test to that file, the CPU seconds it cost (this worker's
    and its reaped child processes', user + system), its wall seconds, its id, when it ended (Unix time) and its
    worker. On 2 cores the suite's wall time is bound by its CPU seconds, which `--durations` does not show (a test
    that waits on a stack costs wall time, not CPU)."""
    path = os.environ.get("GPMPPI_TEST_CPU_LOG")
    if not path:
        yield
        return
    import resource
    import time

    def cpu() -> float:
        own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime

    c0, t0 = cpu(), time.monotonic()
    try:
        yield
    finally:
        with open(path, "a") as f:
            # the end's wall-clock time and the worker last: when the suite's tests ran, and where
            f.write(f"{cpu() - c0:.2f}\t{time.monotonic() - t0:.2f}\t{item.nodeid}\t{time.time():.1f}\t"
                    f"{os.environ.get('PYTEST_XDIST_WORKER', 'main')}\n")



# light tests that open each worker's queue but the first: between two exclusive tests one test of each other
# worker runs, so these cover the exclusive tests at the start without a long test for them to wait on
LEAD_IN = 10


@pytest.hookimpl(trylast=True)  # after `-m` / `-k` deselected: the queues are cut from what runs
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Run order, so that two workers finish together and the exclusive tests wait on no long test.

    pytest-xdist's work stealing hands each worker a contiguous share of this list (the first worker the first
    `n // workers` tests, and so on), and an idle worker takes the last half of a busy one's queue. So the list is
    cut into the workers' shares: the first opens with the `exclusive` tests, the others with `LEAD_IN` light tests;
    then the modules that hold a `slow(seconds=N)` test, dealt out longest first to the share with the least such
    seconds so far (a module stays together, so its module-scoped fixtures are set up once), then the light tests.
    Long tests at the end of a queue were run alone while the other worker idled; an exclusive test among the rest
    waited 55 s for the determinism test. Every worker sorts the same collection the same way."""
    workers = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))

    def seconds(item: pytest.Item) -> float:
        mark = item.get_closest_marker("slow")
        return float(mark.kwargs.get("seconds", 0.0)) if mark is not None else 0.0

    exclusive = [item for item in items if item.get_closest_marker("exclusive") is not None]
    rest = [item for item in items if item.get_closest_marker("exclusive") is None]
    module_seconds: dict[object, float] = {}
    for item in rest:
        if seconds(item) > 0.0:
            module_seconds[item.module] = max(module_seconds.get(item.module, 0.0), seconds(item))
    long_modules: dict[object, list[pytest.Item]] = {module: [] for module in module_seconds}
    light: list[pytest.Item] = []
    for item in rest:
        if item.module in long_modules:
            long_modules[item.module].append(item)
        else:
            light.append(item)

    # the shares' sizes as xdist deals them: each idle worker the remaining tests over the workers still to serve
    sizes, left = [], len(items)
    for k in range(workers):
        sizes.append(left // (workers - k))
        left -= sizes[-1]
    shares: list[list[pytest.Item]] = [list(exclusive)] + [[] for _ in range(workers - 1)]
    for share in shares[1:]:
        share.extend(light[:LEAD_IN])
        del light[:LEAD_IN]
    load = [sum(seconds(item) for item in exclusive)] + [0.0] * (workers - 1)  # the exclusive tests open share 0
    for module in sorted(long_modules, key=lambda m: -module_seconds[m]):  # stable: file order among equals
        k = min(range(workers), key=lambda i: load[i])
        shares[k].extend(long_modules[module])
        load[k] += module_seconds[module]
    for share, size in zip(shares, sizes, strict=True):
        take = max(0, size - len(share))
        share.extend(light[:take])
        del light[:take]
    items[:] = [item for share in shares for item in share] + light
