"""`gpmppi evaluate --ray`: the jobs as Ray tasks give a local run's per-seed scores; bad addresses fail fast.

The Ray instance of these tests is a 2-CPU head started by a child process on loopback only (Ray binds its servers
to the node IP, which is loopback when Ray is told this machine is no cluster node, and each of its processes
inherits that setting), with a token of its own (nothing written to the home folder). Closing the child's stdin
shuts the instance down.
"""

from __future__ import annotations

import json
import math
import os
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict

import numpy as np
import pytest
from typer.testing import CliRunner

from gpmppi.evaluation.runner import EvalSettings, Job, run_job_for_report, summarize
from gpmppi.scenarios import circle_lane, paper_obstacle_scene, square_lane
from tools.cli import app
from tools.evaluate_jobs import make_jobs
from tools.evaluate_ray import RayBackendError, connect, local_copy, run_jobs

LOOPBACK_ENV = {
    # Ray treats this machine as a single local node: node IP, and so every server's bind address, is loopback
    "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0",
    "RAY_AUTH_MODE": "token",
    "RAY_AUTH_TOKEN": secrets.token_hex(16),
}
HEAD = """
import sys, ray
ctx = ray.init(num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1", _temp_dir=sys.argv[1],
               log_to_driver=False)
print(ctx.address_info["gcs_address"], flush=True)
sys.stdin.read()
ray.shutdown()
"""
# tiny trials: what is compared is sameness, not quality
SETTINGS = EvalSettings(samples=128, lane_distance_m=5.0, goal_time_limit_s=8.0)
MODELS = ["gp", "unicycle"]
TIMING = ("planner_ms_mean", "planner_ms_p95")


def _terrain() -> str:
    from cached_models import shipped_model

    return shipped_model().terrains[0]


@pytest.fixture(scope="module", autouse=True)
def loopback() -> Iterator[None]:
    """Every test here: Ray on loopback only (set before this process first imports ray, which reads it then)."""
    saved = {k: os.environ.get(k) for k in LOOPBACK_ENV}
    os.environ.update(LOOPBACK_ENV)
    import ray._private.ray_constants as ray_constants

    cluster = ray_constants.ENABLE_RAY_CLUSTER
    ray_constants.ENABLE_RAY_CLUSTER = False  # where another test module imported ray first
    yield
    ray_constants.ENABLE_RAY_CLUSTER = cluster
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture(scope="module")
def ray_head() -> Iterator[str]:
    """The GCS address (127.0.0.1:PORT) of a fresh 2-CPU Ray instance; the test process talks to it as a driver."""
    temp_dir = tempfile.mkdtemp(prefix="ray-", dir="/tmp")  # short: Ray's socket paths live under it
    head = subprocess.Popen([sys.executable, "-c", HEAD, temp_dir], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True, env=os.environ.copy())
    try:
        address = head.stdout.readline().strip() if head.stdout else ""
        assert address.startswith("127.0.0.1:"), f"the Ray head did not start on loopback: {address!r}"
        yield address
    finally:
        if head.stdin:
            head.stdin.close()
        try:
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            head.kill()
            head.wait()
        shutil.rmtree(temp_dir, ignore_errors=True)


def _jobs_small() -> list[Job]:
    lanes = {"circle": circle_lane(), "square": square_lane()}
    return make_jobs(lanes, {"avoidance": paper_obstacle_scene()}, [_terrain()], MODELS, 2, 2, 0, (), False)


@pytest.fixture(scope="module")
def local_results() -> list[tuple]:
    """`run_job_for_report` of every small job, here, in order."""
    return [run_job_for_report(job, SETTINGS) for job in _jobs_small()]


def _by_seed(results: list[tuple]) -> dict:
    out = {}
    for job, scores, record in results:
        for s in scores:
            d = asdict(s)
            for k in TIMING:
                d.pop(k)
            out[(job.label, job.terrain, job.dynamics, s.seed)] = d
        out[(job.label, job.terrain, job.dynamics, "record")] = record
    return out


def _same(a: object, b: object) -> bool:
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(a, b, equal_nan=True)
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


# compiles the planner kernels where the cache is cold, in this process and in the Ray workers. One test, so that one
# Ray head serves both runs (two tests here could be split between the suite's workers, each then starting a head)
@pytest.mark.slow(seconds=35)  # a Ray head, the jobs here and on Ray, then the CLI on Ray
def test_ray_tasks_give_the_local_runs_scores_seed_by_seed_and_the_cli_reports_them(
    ray_head: str, local_results: list[tuple]
) -> None:
    ray = connect(ray_head)
    try:
        import ray.util

        assert ray.util.get_node_ip_address() == "127.0.0.1"  # this driver, too, stays on loopback
        assert ray.cluster_resources().get("CPU") == 2
        # a task sees writable arrays, as a local worker does (read-only ones make numba compile anew, for minutes)
        writable = ray.remote(lambda job: bool(local_copy(job).scenario.task.obstacles.flags.writeable))
        assert ray.get(writable.remote(_jobs_small()[-1])), "the job's arrays reach the task read-only"
        remote = list(run_jobs(ray, _jobs_small(), SETTINGS))
    finally:
        ray.shutdown()
    local, on_ray = _by_seed(local_results), _by_seed(remote)
    assert on_ray.keys() == local.keys()
    assert len([k for k in local if k[-1] != "record"]) == 2 * 2 * 2 + 2 * 2  # two lanes and the scene, 2 models
    for key in local:
        assert _same(on_ray[key], local[key]), (key, on_ray[key], local[key])
    # and the runs drove: a planner that failed everywhere would compare equal too
    assert any(d["distance_m"] > 3.0 for k, d in local.items() if k[0] == "circle" and k[-1] != "record")

    # the CLI end to end on the same Ray instance (its workers' kernels warm from the runs above)
    terrain = _terrain()
    args = ["evaluate", "tracking", "--json", "-t", terrain, "-m", "gp", "-m", "unicycle", "--trials", "2",
            "--distance", "5", "--samples", "128", "--ray", ray_head]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert "8/8" in res.output  # the progress bar counted every trial
    for job, scores, _ in local_results:
        if job.kind != "tracking":
            continue
        cell = dict(out["results"][job.label][terrain][job.dynamics])
        want = json.loads(json.dumps(summarize(scores), default=float))
        cell.pop("planner_ms"), want.pop("planner_ms")
        assert _same(cell, want), (job.label, job.dynamics, cell, want)


def test_unreachable_address_fails_fast_naming_it() -> None:
    t = time.perf_counter()
    res = CliRunner().invoke(app, ["evaluate", "tracking", "-t", _terrain(), "-m", "unicycle", "--trials", "1",
                                   "--distance", "5", "--ray", "127.0.0.1:1"])
    text = res.output.replace("\n", " ")
    assert res.exit_code == 2, res.output
    assert "127.0.0.1:1" in text and "ray start --head" in text and "--ray auto" in text
    assert time.perf_counter() - t < 30.0


def test_a_port_that_is_no_ray_cluster_fails_within_the_probe_timeout() -> None:
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    conns: list[socket.socket] = []

    def accept() -> None:
        while True:
            try:
                conns.append(server.accept()[0])  # answer TCP, never speak Ray
            except OSError:
                return

    threading.Thread(target=accept, daemon=True).start()
    t = time.perf_counter()
    try:
        with pytest.raises(RayBackendError, match=f"127.0.0.1:{port}.*not as a Ray cluster: no HTTP/2 "):
            connect(f"127.0.0.1:{port}")
    finally:
        server.close()
        for c in conns:
            c.close()
    # the HTTP/2 handshake probe's 2 s, not Ray's own GCS client (~15 s), with Ray's import before it
    assert time.perf_counter() - t < 12.0


def test_missing_ray_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    with pytest.raises(RayBackendError, match=r"\.\[ray\]"):
        connect("auto")
