"""`gpmppi evaluate ... --ray [auto|ADDRESS]`: the evaluation's jobs as Ray tasks on an existing Ray cluster.

The tasks run the same job function as the local worker pool (`run_job_for_report`), with the same seeds, so
every trial's scores are those of a local run; only the planner timings differ (other machines, other load).
Ray is an optional dependency (the `ray` extra) and is imported only here, only when `--ray` is given.

Every node of the cluster needs this same gpmppi installed (the tasks import it) and, to start in seconds, a warm
kernel cache (`gpmppi warm` on each node: numba compiles the kernels in every process that finds the cache cold).
"""

from __future__ import annotations

import copy
import logging
import os
import socket
from collections.abc import Iterator
from typing import Any

from gpmppi.evaluation.runner import EvalSettings, Job, init_worker, run_job_for_report

INSTALL_HINT = "pip install -e '.[ray]' (or pip install 'ray>=2.40')"
# Ray's own connect retries for minutes where no Ray cluster answers; the probes before it bound that. Each may
# take this long (a refused connection answers at once, a dropped one waits; the GCS handshake retries ~3 times)
PROBE_TIMEOUT_S = 5.0
# a Ray cluster's GCS is a gRPC server, so HTTP/2: it answers a client's connection preface with its SETTINGS frame
# at once. A port that answers TCP but not that fails within this, before Ray's own GCS client (which waited ~15 s)
HANDSHAKE_TIMEOUT_S = 2.0
_H2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])  # + an empty SETTINGS frame
_H2_SETTINGS = 4  # the frame type of SETTINGS (RFC 9113, 6.5)


class RayBackendError(RuntimeError):
    """Ray is missing, or no Ray cluster answers at the address: the message says which and what to do."""


def _import_ray() -> Any:
    try:
        import ray
    except ImportError as e:
        raise RayBackendError(f"--ray needs Ray, which is not installed ({e}); install the ray extra: "
                              f"{INSTALL_HINT}") from e
    return ray


def _not_found(address: str, why: str) -> RayBackendError:
    lead = (f"--ray auto: no running Ray cluster found ({why})" if address == "auto"
            else f"--ray {address}: no Ray cluster answers there ({why})")
    return RayBackendError(
        f"{lead}. Start one (`ray start --head` on the head node, `ray start --address HEAD:6379` on the others) "
        "and pass the head's address (HOST:PORT of its GCS, port 6379 unless `ray start --port` said otherwise), "
        "or `--ray auto` on a node of the cluster; or drop --ray to run on local worker processes."
    )


def _split_host_port(address: str) -> tuple[str, int] | None:
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def resolve_address(address: str) -> str:
    """The HOST:PORT Ray will connect to for `address` (`auto`: RAY_ADDRESS, else the cluster this node joined)."""
    if address == "auto" and os.environ.get("RAY_ADDRESS", "").startswith("ray://"):
        address = os.environ["RAY_ADDRESS"]
    if address.startswith("ray://"):
        return address
    try:
        from ray._private.services import canonicalize_bootstrap_address_or_die
    except ImportError:  # another Ray version: connect to what was given, unresolved
        return address
    try:
        return canonicalize_bootstrap_address_or_die(address)
    except ConnectionError as e:
        raise _not_found(address, str(e).split(". ")[0]) from e
    except ValueError as e:
        raise RayBackendError(f"--ray {address}: not a Ray address ({e}); give HOST:PORT, ray://HOST:PORT or auto") \
            from e


def probe(address: str, resolved: str) -> None:
    """Fail fast where nothing listens at `resolved`, and where what listens is not a Ray cluster's GCS."""
    hostport = _split_host_port(resolved.removeprefix("ray://"))
    if hostport is None:
        raise RayBackendError(f"--ray {address}: expected HOST:PORT, ray://HOST:PORT or auto")
    where = address if address == resolved else f"{address} ({resolved})"
    try:
        conn = socket.create_connection(hostport, timeout=PROBE_TIMEOUT_S)
    except OSError as e:
        raise _not_found(where, e.strerror or type(e).__name__) from e
    with conn:
        if resolved.startswith("ray://"):
            return  # a Ray Client server, not a GCS: ray.init's own handshake decides there
        if os.environ.get("RAY_USE_TLS", "0").lower() not in ("1", "true"):  # TLS: the GCS client below decides
            frame = _http2_first_frame(conn)
            if frame is None or frame[3] != _H2_SETTINGS:
                raise _not_found(where, "the port answers, but not as a Ray cluster: no HTTP/2 (gRPC) handshake "
                                        f"within {HANDSHAKE_TIMEOUT_S:.0f} s")
    try:
        from ray._raylet import InnerGcsClient

        standalone = InnerGcsClient.standalone
    except (ImportError, AttributeError):  # another Ray version: the port answers, leave the rest to ray.init
        return
    try:
        standalone(resolved, None, int(PROBE_TIMEOUT_S * 1000))
    except Exception as e:  # Ray's RpcError has no stable public name across versions
        raise _not_found(where, f"the port answers, but not as a Ray cluster: {e}") from e


def _http2_first_frame(conn: socket.socket) -> bytes | None:
    """The 9-byte header of the first frame a server sends after an HTTP/2 client preface, or None when it sends
    none within `HANDSHAKE_TIMEOUT_S` (or closes the connection)."""
    conn.settimeout(HANDSHAKE_TIMEOUT_S)
    header = b""
    try:
        conn.sendall(_H2_PREFACE)
        while len(header) < 9:
            chunk = conn.recv(9 - len(header))
            if not chunk:
                return None
            header += chunk
    except OSError:  # a timeout, or the connection reset
        return None
    return header


def connect(address: str) -> Any:
    """Connect this process to the Ray cluster at `address` (`auto`, HOST:PORT or ray://HOST:PORT); the ray module.

    Bounded in time: an address where no cluster answers fails within a few probe timeouts, naming the address.
    """
    ray = _import_ray()
    resolved = resolve_address(address)
    probe(address, resolved)
    try:
        # the workers' output stays in the cluster's logs: the driver shows the progress bar, as a local run does
        ray.init(address=resolved, log_to_driver=False, logging_level=logging.WARNING)
    except Exception as e:  # connection, version or authentication errors: Ray's own message says which
        raise RayBackendError(f"--ray {address}: connecting to the Ray cluster at {resolved} failed: {e}") from e
    return ray


def local_copy(job: Job) -> Job:
    """`job` as a local worker gets it: Ray hands a task its arguments' numpy arrays read-only (zero-copy from the
    object store), and numba compiles a kernel anew, for minutes in every worker, for read-only array types that
    `gpmppi warm` and the local runs never compiled; a copy has writable arrays."""
    return copy.deepcopy(job)


def _job_task(job: Job, settings: EvalSettings, threads: int) -> tuple:
    """One job in a Ray worker: the local pool's initializer, then its job function."""
    init_worker(threads)
    return run_job_for_report(local_copy(job), settings)


def run_jobs(ray: Any, jobs: list[Job], settings: EvalSettings, cpus_per_job: int = 1) -> Iterator[tuple]:
    """Submit every job as a Ray task (one CPU each) and yield `run_job_for_report`'s results as tasks complete.

    A job that fails cancels the others and raises its error here, as a local worker's error does.
    """
    task = ray.remote(num_cpus=cpus_per_job, max_retries=0)(_job_task)
    settings_ref = ray.put(settings)
    # long lane jobs first, so the cluster does not end on one long straggler (the local pool's order)
    ordered = sorted(jobs, key=lambda j: j.kind != "tracking")
    pending = [task.remote(job, settings_ref, cpus_per_job) for job in ordered]
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                yield ray.get(ref)
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
