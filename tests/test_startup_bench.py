"""`gpmppi bench startup`'s measurement: a service restarted on its own while the stack runs, on loopback.
Structure only (no timing thresholds): the number recorded is the new process's first output, which an
independent outside client sees too."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
import yaml
import zenoh
from zenoh_helpers import Collector, client, free_port

from schemas import State, decode
from tools.bench_startup import measure_startup


def _observe(port: int, key: str, stop: threading.Event, out: list[Collector]) -> None:
    """An outside client of the launcher's router, joining once the router is up."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not stop.is_set():
        try:
            session = client(port)
        except zenoh.ZError:
            time.sleep(0.1)
            continue
        out.append(Collector(session, key))
        stop.wait(120)
        session.close()
        return


@pytest.mark.slow(seconds=12)  # a service started, killed and started again, timed to its first output
def test_restarted_service_first_output_is_from_the_new_process(tmp_path: Path) -> None:
    port = free_port()
    launch = tmp_path / "sim_only.yaml"
    launch.write_text(
        yaml.safe_dump(
            {
                "robot": "r1",
                "router": {"listen": [f"tcp/127.0.0.1:{port}"]},
                "zenoh": {"connect": [f"tcp/127.0.0.1:{port}"]},
                "services": [{"name": "sim", "config": {"terrain": "asphalt", "lane": "circle", "publish_hz": 10.0}}],
            }
        )
    )
    key = "gpmppi/r1/odom/raw"
    stop = threading.Event()
    collectors: list[Collector] = []
    side = threading.Thread(target=_observe, args=(port, key, stop, collectors), daemon=True)
    side.start()
    try:
        result = measure_startup(launch, ["sim"], repeats=2, settle_s=1.5, timeout_s=30.0, port=port)
    finally:
        stop.set()
        side.join(10)
    assert result.exit_code == 0
    assert result.summary is not None and "sim" in result.summary.first_output_s  # the cold start, as today
    assert len(result.load_avg_1min) == 2

    first, second = result.restarts
    assert [r.service for r in result.restarts] == ["sim", "sim"]
    # each restart replaced the process: new pids, the second restart stopped the first one's process
    assert len({first.old_pid, first.pid, second.pid}) == 3 and second.old_pid == first.pid
    for r in result.restarts:
        assert r.first_output_s is not None and 0.0 < r.first_output_s < 30.0
        assert r.stop_s >= 0.0
        # the old process had published for the settling time; the new one counts from 0 again
        # (>= 2, not 5: 15 at 10 Hz over the settling time on an idle machine, 4 once at a load average of 6)
        assert r.old_last_seq is not None and r.old_last_seq >= 2
        assert r.first_seq is not None and r.first_seq < r.old_last_seq
    rows = result.per_service()
    assert list(rows) == ["sim"] and rows["sim"]["n"] == 2 and rows["sim"]["timeouts"] == 0
    assert rows["sim"]["p50_s"] is not None and rows["sim"]["p50_s"] <= rows["sim"]["max_s"]
    data = result.to_json()
    assert data["restart_first_output_s"]["sim"]["n"] == 2 and len(data["restart_load_avg_1min"]) == 2

    # an independent client saw the same thing: the sequence numbers on the output key start again exactly twice,
    # and the last message before each restart and the first after it are the ones the measurement names
    assert collectors, "the outside client never connected"
    seqs = [decode(State, payload).header.seq for _, payload, _ in collectors[0].on(key)]
    resets = [i for i in range(1, len(seqs)) if seqs[i] < seqs[i - 1]]
    assert len(resets) == 2, seqs
    for i, r in zip(resets, result.restarts, strict=True):
        assert (seqs[i - 1], seqs[i]) == (r.old_last_seq, r.first_seq), (seqs, r)


def test_unknown_service_is_refused() -> None:
    with pytest.raises(ValueError, match="recorder"):
        measure_startup(None, ["recorder"])


def test_process_age_counts_from_process_creation() -> None:
    import subprocess
    import sys

    from services.runtime.scheduling import process_age_s

    before = process_age_s()
    time.sleep(0.3)
    after = process_age_s()
    assert before is not None and after is not None and 0.25 <= after - before <= 5.0
    # this test process was created before the test began; a new one reports an age smaller than ours
    code = "from services.runtime.scheduling import process_age_s; print(process_age_s())"
    fresh = float(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)
    assert 0.0 <= fresh < after
