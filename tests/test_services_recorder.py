"""recorder and ingress (sim source) as processes: a burst is recorded without drops, a killed recorder
leaves a readable file, rotation; ingress rejects stale / non-finite / implausible odometry."""

from __future__ import annotations

import time
from pathlib import Path

import zenoh
from zenoh_helpers import (
    Collector,
    ServiceProcess,
    client,
    free_port,
    heartbeats,
    matched_publisher,
    router,
    settings,
    wait_for,
)

from schemas import Command, Header, State, decode, encode
from services.mcap_io import read_messages, recording_files


def _publish_burst(port: int, n: int) -> None:
    s = client(port)
    pub = matched_publisher(s, "gpmppi/r1/cmd", congestion_control=zenoh.CongestionControl.BLOCK)
    for i in range(n):
        pub.put(encode(Command(header=Header(seq=i), v_ref=0.001 * i, omega_ref=0.0)))
    s.close()


def test_recorder_keeps_a_burst_and_rotates(tmp_path: Path) -> None:
    port = free_port()
    path = tmp_path / "rec.mcap"
    with router(port):
        observer = client(port)
        col = Collector(observer)
        rec = ServiceProcess(
            "recorder", settings("recorder", port, path=str(path), max_bytes=60_000, chunk_size=8_000), tmp_path
        )
        try:
            assert wait_for(lambda: bool(heartbeats(col, "r1", "recorder")), 15.0), rec.log()
            _publish_burst(port, 3000)
            assert wait_for(lambda: len(col.on("gpmppi/r1/cmd")) == 3000, 10.0)
            time.sleep(1.0)
        finally:
            assert rec.stop() == 0
            observer.close()
    assert len(recording_files(path)) >= 2
    cmds = [m for k, _, m in read_messages(path) if k == "gpmppi/r1/cmd"]
    assert [m.v_ref for m in cmds] == [0.001 * i for i in range(3000)]
    assert any(k == "gpmppi/r1/health/recorder" for k, _, _ in read_messages(path))


def test_killed_recorder_leaves_a_readable_file(tmp_path: Path) -> None:
    port = free_port()
    path = tmp_path / "crash.mcap"
    with router(port):
        observer = client(port)
        col = Collector(observer)
        rec = ServiceProcess("recorder", settings("recorder", port, path=str(path), flush_interval_s=0.2), tmp_path)
        try:
            assert wait_for(lambda: bool(heartbeats(col, "r1", "recorder")), 15.0), rec.log()
            _publish_burst(port, 500)
            time.sleep(1.0)  # > flush_interval_s: the data is on disk
            rec.process.kill()  # no chance to finish the file
            rec.process.wait(5)
        finally:
            rec.stop()
            observer.close()
    cmds = [m for k, _, m in read_messages(path) if k == "gpmppi/r1/cmd"]
    assert len(cmds) == 500


def test_ingress_sim_source_rejects_bad_odometry(tmp_path: Path) -> None:
    port = free_port()
    with router(port):
        observer = client(port)
        col = Collector(observer)
        ingress = ServiceProcess("ingress", settings("ingress", port, max_age_s=0.5), tmp_path)
        try:
            assert wait_for(lambda: bool(heartbeats(col, "r1", "ingress")), 15.0), ingress.log()
            pub = matched_publisher(observer, "gpmppi/r1/odom/raw")
            now = time.time_ns()
            bad = [
                b'{"x": NaN, "y": 0, "theta": 0, "v": 0, "omega": 0}',
                encode(State(header=Header(stamp_ns=now - 2_000_000_000), x=0, y=0, theta=0, v=0, omega=0)),
                encode(State(header=Header(stamp_ns=now), x=0, y=0, theta=0, v=50.0, omega=0)),
                encode(State(header=Header(stamp_ns=now + 10_000_000_000), x=0, y=0, theta=0, v=0, omega=0)),
            ]
            for payload in bad:
                pub.put(payload)
                time.sleep(0.2)
            good = State(header=Header(stamp_ns=time.time_ns(), frame_id="odom"), x=1, y=2, theta=4.0, v=1, omega=0)
            pub.put(encode(good))
            assert wait_for(lambda: bool(col.on("gpmppi/r1/state")), 5.0), ingress.log()
            assert wait_for(lambda: any(h.rejected >= 4 for h in heartbeats(col, "r1", "ingress")), 3.0)
        finally:
            assert ingress.stop() == 0
            observer.close()
    states = [decode(State, p) for _, p, _ in col.on("gpmppi/r1/state")]
    assert len(states) == 1 and (states[0].x, states[0].y) == (1.0, 2.0)
    assert -3.1416 < states[0].theta < 0.0  # 4.0 rad wrapped to (-pi, pi]
    log = ingress.log()
    assert "stale" in log and "implausible" in log and "future" in log and "finite" in log
