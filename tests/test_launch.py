"""The launcher: the whole stack on loopback (every heartbeat, every key in the MCAP, lane tracking close to
the in-process evaluation, a real .rrd), restarts and failure, and the shipped deploy files."""

from __future__ import annotations

import io
import json
import math
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
import zenoh
from mcap.reader import make_reader
from zenoh_helpers import client, free_port, wait_for, without_spares

from gpmppi.evaluation.metrics import lane_rmse_mm
from gpmppi.scenarios import circle_lane
from schemas import KEYS, EStop, encode, key_for
from services.launch.launch_file import DEFAULT_LAUNCH, LaunchFile
from services.launch.launcher import run_launch
from services.recording.mcap_io import read_messages
from services.run import settings_class

REPO = Path(__file__).resolve().parents[1]
SERVICES = ["sim", "ingress", "terrain", "planner", "egress", "recorder", "viewer"]


def _in_process_rmse(duration_s: float, latency_s: float) -> float:
    """The same scenario (circle lane, asphalt, the services' model) in one process, no middleware: the
    mean over seeds 0-4 (one short run's RMSE moves by several mm with the seed: 20-33 mm over 12 seeds, so a
    reference from one seed alone could decide a 1.5x comparison).

    Scored like the recording: on the measured (noisy) positions the stack publishes as `state`, with
    the stack's median state -> command latency, so the comparison isolates what Zenoh and the
    process split add.
    """
    from cached_models import shipped_model

    from gpmppi.evaluation.closed_loop import ClosedLoopConfig, run_closed_loop
    from gpmppi.gp.model_file import GPModel
    from gpmppi.mppi.planner import Planner, PlannerConfig
    from gpmppi.plant.physics import PhysicsPlant
    from gpmppi.plant.terrains import load_terrains
    from gpmppi.terrain.least_squares import TerrainEstimator

    # the services take GPMPPI_MODEL_FILE from the environment (settings override), so the reference does too
    path = os.environ.get("GPMPPI_MODEL_FILE")
    model = GPModel.load(path) if path else shipped_model()
    scenario = circle_lane()
    rmse = []
    for seed in range(5):
        traj = run_closed_loop(
            Planner(PlannerConfig(seed=seed), model),
            PhysicsPlant(load_terrains(None), "asphalt", seed=seed),
            scenario.task,
            scenario.start,
            len(model.terrains),
            ClosedLoopConfig(time_limit_s=duration_s, latency_s=latency_s),
            estimator=TerrainEstimator(model),
        )
        rmse.append(lane_rmse_mm(traj.measured_states[:, :2], scenario.task.centerline, closed=True))
    return float(np.mean(rmse))


@pytest.mark.slow(seconds=60)  # the whole stack over Zenoh for 30 s
# alone: it compares its tracking with the in-process run at the latency it measured, and a test beside it is load
# that moves the stack's latency tails (17 mm against 13 once, 10.5-11.4 alone)
@pytest.mark.exclusive
def test_whole_stack_on_loopback(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    port = free_port()
    record, rrd = tmp_path / "run.mcap", tmp_path / "run.rrd"
    out = io.StringIO()
    result: dict = {}

    bad_inputs = {
        "state": [
            b"{bad json",
            b'{"x": NaN, "y": 0, "theta": 0, "v": 0, "omega": 0}',
            b'{"header": {"schema_version": 7}, "x": 0, "y": 0, "theta": 0, "v": 0, "omega": 0}',
        ],
        "task": [b'{"kind": "lane", "centerline": [[0, 0]]}'],
        "terrain_weights": [b'{"names": ["asphalt", "grass", "tile"], "weights": [1.0, 1.0, 1.0]}'],
    }

    def outside_client() -> None:
        # joins once the planner is up: releases the e-stop (so the estop key is on the wire too) and sends
        # bad input on the keys the planner subscribes to
        deadline = time.monotonic() + 600
        s = None
        while s is None and time.monotonic() < deadline:
            try:
                s = client(port)
            except zenoh.ZError:
                time.sleep(0.2)
        if s is None:
            return
        planner_up = threading.Event()
        sub = s.declare_subscriber(key_for("health", service="planner"), lambda _: planner_up.set())
        planner_up.wait(max(0.0, deadline - time.monotonic()))
        time.sleep(1.0)
        pub = s.declare_publisher(key_for("estop"))
        for _ in range(3):
            pub.put(encode(EStop(engaged=False, reason="test")))
            time.sleep(0.3)
        for name, payloads in bad_inputs.items():
            bad_pub = s.declare_publisher(key_for(name))
            for payload in payloads:
                bad_pub.put(payload)
                time.sleep(0.3)
        sub.undeclare()
        s.close()

    side = threading.Thread(target=outside_client, daemon=True)
    side.start()
    code, summary = run_launch(None, duration=30.0, record=str(record), rerun=["save", str(rrd)], port=port, out=out,
                               edit=without_spares)
    side.join(5)
    result["log"] = out.getvalue()
    assert code == 0, result["log"][-4000:]
    assert set(summary.heartbeats_from) >= set(SERVICES), summary.heartbeats_from
    assert summary.restarts == {} and summary.failed == []
    # the recording holds every registered key (health for each service)
    recorded = {key for key, _, _ in read_messages(record)}
    # (a costmap is published only with a goal task among a grid; this launch drives a lane; a learn request and a
    # model update only when a ground is learned: tests/test_online_ground_service.py, deploy/new_ground_demo.yaml)
    expected = {key_for(name) for name in KEYS if name not in ("health", "costmap", "ground_learn", "model_update")}
    expected |= {key_for("health", service=s) for s in SERVICES}
    assert expected <= recorded, f"missing from the MCAP: {expected - recorded}"
    # the planner counted the bad input, kept running, and every command on the wire is valid and finite
    planner_hb = [m for _, _, m in read_messages(record, [key_for("health", service="planner")])]
    # every one: a bad state replaced by a good one before the loop took it is counted on arrival (`Inbox`)
    assert planner_hb[-1].rejected >= sum(len(v) for v in bad_inputs.values()), planner_hb[-1]
    with open(record, "rb") as f:
        raw = [
            (c.topic, m.data) for _, c, m in make_reader(f).iter_messages(topics=[key_for("cmd"), key_for("base_cmd")])
        ]
    assert len(raw) > 50
    for topic, data in raw:
        values = json.loads(data)
        numbers = [values["v_ref"], values["omega_ref"]] if topic.endswith("/cmd") and "v_ref" in values else []
        numbers += [values["v"], values["omega"]] if "v" in values else []
        assert numbers and all(isinstance(x, float | int) and math.isfinite(x) for x in numbers), data
    # the robot drove the lane: compare with the in-process evaluation of the same scenario over the same time,
    # counted from the planner's first command (before it the robot waits at the start, on the centre line)
    first_cmd = min(m.header.stamp_ns for _, _, m in read_messages(record, [key_for("cmd")]))
    states = sorted((m.header.stamp_ns, m.x, m.y) for _, _, m in read_messages(record, [key_for("state")]))
    xy = np.array([[x, y] for t, x, y in states if t >= first_cmd])
    driven_s = (states[-1][0] - first_cmd) / 1e9
    assert driven_s > 8.0 and summary.distance_driven_m > 5.0 and np.all(np.isfinite(xy))
    assert summary.lane_exits == 0
    over_zenoh = lane_rmse_mm(xy, circle_lane().task.centerline, closed=True)
    assert summary.latency_p50_ms is not None
    reference = _in_process_rmse(driven_s, summary.latency_p50_ms / 1e3)
    # a real .rrd: rerun reads it back with the map and plot entities
    from rerun.chunk import RrdReader

    paths = {str(c.entity_path) for c in RrdReader(rrd).stream().to_chunks()}
    assert {"/map/robot", "/map/plan/nominal", "/map/lane/edges", "/plots/v/state"} <= paths
    # the stack plans for the state its command meets (each state's age + compute + actuation), the reference for
    # the state after the stack's median latency: both compensate the latency they have
    # 1.2x (issue "Evaluate what the robot runs"): with the smooth update, the applied-command pairing and the
    # retrained model the stack tracks as the reference does: 10.5 / 11.4 / 11.0 mm over Zenoh against 13.1 mm in
    # process, three runs (0.80-0.87x); the deployed-path evaluation of the same seconds gave 13.0 mm. It was 2x
    # while the stack lagged (43-46 against 25-29 mm). Over 30 s at 5fc2bd9: 10.0-13.1 mm in six runs, against 12.5
    print(f"\nlane RMSE over Zenoh {over_zenoh:.1f} mm, in process {reference:.1f} mm at the stack's p50 latency "
          f"{summary.latency_p50_ms:.0f} ms; planner {summary.planner_rate_hz} Hz, p99 {summary.latency_p99_ms} ms")
    # (a failure says whether the stack fell behind: a planner below 10 Hz skipped states the reference planned)
    assert over_zenoh <= 1.2 * reference, (
        f"over Zenoh {over_zenoh:.0f} mm vs in-process {reference:.0f} mm; planner {summary.planner_rate_hz} Hz, "
        f"state -> command p50 {summary.latency_p50_ms} ms p99 {summary.latency_p99_ms} ms")
    # the terrain service reads the sim's asphalt from the drive (issue "Evaluate what the robot runs": 0.67 in the
    # stack before; 0.95 with the response evidence in 40 s launches): the recorded weights. Since the estimator takes
    # no evidence from the start from rest (which read asphalt on every terrain), it tells asphalt from tile only as
    # the circle's yaw response accumulates: in one 15 s run tile led from 6 to 11 s and asphalt took the top for
    # good at 14.6 s (0.79 over the last 2 s). So 30 s, and where the identification ends, not the window mean, which
    # moves run to run (six 30 s runs at 5fc2bd9: mean 0.77-0.87 after 3 s; over the last 2 s 0.95-0.96, asphalt
    # >= 0.93 through the last 5 s). The window metrics (>= 0.8, <= 2 changes a minute) are the evaluation's, over
    # 100 m (asphalt circle 0.90, 1.17; docs/terrain_identification.md)
    from tools.stack_terrain import load, scores

    log = load(record)
    names = ["asphalt", "grass", "tile"]
    stamps = [stamp for stamp, _, _ in log["states"]]
    weights = {stamp: np.array([w[n] for n in names]) for stamp, w, _ in log["weights"] if set(w) == set(names)}
    named = {stamp: top_named for stamp, _, top_named in log["weights"]}
    identified = scores(stamps, weights, ["asphalt"] * len(stamps), names, named)
    updates = sorted((stamp, w) for stamp, w in weights.items() if stamp >= stamps[0])
    end_ns = updates[-1][0]
    last_2s = np.mean([w for stamp, w in updates if stamp > end_ns - 2e9], axis=0)
    print(f"asphalt identified: {identified}; the last 2 s {np.round(last_2s, 3).tolist()}")
    assert int(np.argmax(identified["mean_weights"])) == names.index("asphalt"), identified
    assert last_2s[names.index("asphalt")] >= 0.85, (last_2s, identified)
    tops = {names[int(np.argmax(w))] for stamp, w in updates if stamp > end_ns - 5e9}
    assert tops == {"asphalt"}, (tops, identified)
    assert summary.planner_rate_hz is not None and summary.planner_rate_hz > 2.0
    assert summary.latency_p99_ms is not None and "lane, RMSE" in result["log"]
    # the planner's own stamp -> publish latency comes before any session receives the command (one clock)
    assert summary.delivery_p50_ms is not None and summary.latency_p50_ms <= summary.delivery_p50_ms


def test_crashing_required_service_fails_the_launch(tmp_path: Path) -> None:
    launch = tmp_path / "bad.yaml"
    port = free_port()
    launch.write_text(
        yaml.safe_dump(
            {
                "router": {"listen": [f"tcp/127.0.0.1:{port}"]},
                "zenoh": {"connect": [f"tcp/127.0.0.1:{port}"]},
                "max_restarts": 2,
                "restart_backoff_s": 0.1,
                "services": [
                    {"name": "egress"},
                    # settings that validate (a bad one is refused before anything starts) but fail at the
                    # service's start: a terrain its terrain set does not have
                    {"name": "sim", "config": {"terrain": "nowhere"}},
                ],
            }
        )
    )
    out = io.StringIO()
    t0 = time.monotonic()
    code, summary = run_launch(launch, duration=30.0, out=out)
    log = out.getvalue()
    assert code == 1, log[-3000:]
    # early: before the launch's own end at 30 s; three starts of a failing process fit well inside it
    assert time.monotonic() - t0 < 29.0, "a required service failing for good must stop the launch early"
    assert summary.restarts.get("sim") == 2 and summary.failed == ["sim"]
    assert "restart 1 in 0.1 s" in log and "restart 2 in 0.2 s" in log and "failed for good" in log
    assert "service failed" in log and "unknown terrain 'nowhere'" in log
    # everything else was stopped in reverse order, politely
    assert log.index("stopped egress") < log.index("stopped router")


def test_shipped_launch_and_deploy_files_validate(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)
    for path in [DEFAULT_LAUNCH, *sorted((REPO / "deploy").glob("*.yaml"))]:
        launch = LaunchFile.load(path)
        assert launch.services, path
        for entry in launch.services:
            kind = entry.kind or entry.name
            settings_class(kind).model_validate({**entry.config, "service": entry.name})
        if launch.router.enabled:
            settings_class("router").model_validate({"listen": launch.router.listen, **launch.router.config})
        if launch.zenoh.config_file:
            launch.zenoh.to_config()
    for path in sorted((REPO / "deploy" / "zenoh").glob("*.json5")):
        zenoh.Config.from_file(str(path))
    for path in sorted((REPO / "deploy" / "systemd" / "etc").glob("*.yaml")):
        settings_class(path.stem).model_validate(yaml.safe_load(path.read_text()))
    unit = (REPO / "deploy" / "systemd" / "gpmppi@.service").read_text()
    assert "KillSignal=SIGINT" in unit and "Restart=on-failure" in unit and "PartOf=gpmppi.target" in unit


def test_monitor_summary_reads_json_logs() -> None:
    from services.launch.processes import readable

    line = json.dumps({"t": 1.0, "level": "WARNING", "service": "x", "logger": "l", "msg": "hello", "n": 3})
    assert readable(line) == "WARNING hello n=3"
    assert readable("plain text\n") == "plain text\n"
    assert wait_for(lambda: True, 0.1)
