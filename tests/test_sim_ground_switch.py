"""The sim service's ground schedule (`terrain_switches`): the ground changes mid-run in a real sim process (its
`TerrainLabel` and the plant's response), and a launch file whose switch names a ground the terrain set lacks is
refused in one line before anything starts."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from zenoh_helpers import Collector, ServiceProcess, client, free_port, matched_publisher, router, settings, wait_for

from schemas import BaseCommand, Header, State, TerrainLabel, decode, encode
from services.launch.launch_file import LaunchFileError, check_profile_grounds, load_launch
from services.launch.launcher import check_launch
from services.sim import Settings

REPO = Path(__file__).resolve().parents[1]
SWITCH_S = 2.0


def test_the_schedule_switches_the_ground_label_and_response(tmp_path: Path) -> None:
    port = free_port()
    config = settings("sim", port, terrain="asphalt", publish_hz=50.0, noise=False,
                      terrain_switches=[{"at_s": SWITCH_S, "terrain": "sand"}])
    with router(port):
        observer = client(port)
        col = Collector(observer)
        sim = ServiceProcess("sim", config, tmp_path)
        try:
            assert wait_for(lambda: bool(col.on("gpmppi/r1/odom/raw")), 20.0), sim.log()
            pub = matched_publisher(observer, "gpmppi/r1/base/cmd")
            # drive straight at 1 m/s (20 Hz, as egress sends) until 2.5 s after the switch is seen: counted from
            # the switch's label, not from the first output (a sim slowed by load switched at least 1.5 s later than
            # that count, and the drive ended before a second of sand)
            deadline, end = time.monotonic() + SWITCH_S + 60.0, None
            while time.monotonic() < (end or deadline):
                pub.put(encode(BaseCommand(v=1.0, omega=0.0, header=Header(stamp_ns=time.time_ns()))))
                time.sleep(0.05)
                if end is None and any(decode(TerrainLabel, p).terrain == "sand"
                                       for _, p, _ in col.on("gpmppi/r1/terrain/label")[-3:]):
                    end = time.monotonic() + 2.5
        finally:
            assert sim.stop() == 0
            observer.close()
    labels = [(t, decode(TerrainLabel, p).terrain) for t, p, _ in col.on("gpmppi/r1/terrain/label")]
    names = [n for _, n in labels]
    assert names[0] == "asphalt" and names[-1] == "sand", names
    first_sand = names.index("sand")
    assert set(names[first_sand:]) == {"sand"}, "the ground switched back"
    t_switch = labels[first_sand][0]
    assert "ground switched from 'asphalt' to 'sand'" in sim.log()
    odom = [(t, decode(State, p).v) for t, p, _ in col.on("gpmppi/r1/odom/raw")]
    before = np.array([v for t, v in odom if t_switch - 0.5 <= t < t_switch])
    after = np.array([v for t, v in odom if t >= odom[-1][0] - 0.5 and t > t_switch + 1.0])
    assert before.size > 5 and after.size > 5, (before, after)
    print(f"speed at 1 m/s commanded: asphalt {before.mean():.3f} m/s, sand {after.mean():.3f} m/s")
    # the same command, another ground: sand's drag and sinkage take speed off (asphalt ~1 m/s)
    assert before.mean() > 0.9, before
    assert after.mean() < before.mean() - 0.05, (before.mean(), after.mean())


def test_a_switch_to_a_ground_the_terrain_set_lacks_is_refused_in_one_line(tmp_path: Path) -> None:
    launch_file = tmp_path / "launch.yaml"
    switches = [{"at_s": 5, "terrain": "asphalt"}, {"at_s": 9, "terrain": "dune"}]
    launch_file.write_text(yaml.safe_dump(
        {"services": [{"name": "sim", "config": {"terrain": "asphalt", "terrain_switches": switches}}]}))
    launch, marks = load_launch(launch_file)
    with pytest.raises(LaunchFileError) as err:
        check_launch(launch, launch_file, marks)
    message = str(err.value)
    assert "\n" not in message and f"{launch_file}:" in message and "terrain_switches" in message, message
    assert "'dune'" in message and "terrain set lacks" in message and "sand" in message, message
    # out of time order, a negative time: refused too, by name
    with pytest.raises(ValueError, match="time order"):
        Settings(terrain_switches=[{"at_s": 9, "terrain": "sand"}, {"at_s": 5, "terrain": "grass"}])
    with pytest.raises(ValueError, match="at_s"):
        Settings(terrain_switches=[{"at_s": -1, "terrain": "sand"}])


def test_the_demo_launch_file_switches_to_a_ground_its_profile_lacks(tmp_path: Path) -> None:
    """deploy/new_ground_demo.yaml: sand is allowed (that is the point) and noted; the starting ground is checked."""
    demo = yaml.safe_load((REPO / "deploy" / "new_ground_demo.yaml").read_text())
    profile = tmp_path / "ng_profile.npz"
    profile.write_bytes((REPO / "gpmppi" / "data" / "default_gp_model.npz").read_bytes())
    demo["profile"] = str(profile)
    launch_file = tmp_path / "demo.yaml"
    launch_file.write_text(yaml.safe_dump(demo))
    launch, marks = load_launch(launch_file)
    check_launch(launch, launch_file, marks)
    notes = check_profile_grounds(launch, launch_file)
    assert len(notes) == 1 and "'sand'" in notes[0] and "profile lacks" in notes[0], notes
    demo["services"][0]["config"]["terrain"] = "sand"  # the starting ground must be one the profile has (issue 41)
    launch_file.write_text(yaml.safe_dump(demo))
    with pytest.raises(LaunchFileError, match="names ground 'sand', which the profile"):
        check_profile_grounds(load_launch(launch_file)[0], launch_file)


def test_the_timeline_reads_the_change_the_detection_the_update_and_the_rmse(tmp_path: Path) -> None:
    """tools.new_ground_timeline on a recording made here (10 Hz, 30 s): the numbers it reports come from it."""
    from gpmppi.scenarios import lane_scenario
    from schemas import ModelUpdate, TerrainWeights
    from services.recording.mcap_writer import McapWriter
    from tools.new_ground_timeline import timeline

    centre = np.asarray(lane_scenario("circle").task.centerline)
    path = tmp_path / "ng.mcap"
    with McapWriter(path) as w:
        for i in range(300):
            t, ns = i / 10, 10**9 + i * 10**8
            ground = "asphalt" if t < 10 else "sand"
            w.write("gpmppi/jackal/terrain/label", TerrainLabel(terrain=ground), ns)
            # on the centre line, 20 mm off it on the new ground before the update
            off = 0.02 if 10 <= t < 20 else 0.0
            p = centre[i % len(centre)] * (1 + off / np.linalg.norm(centre[i % len(centre)]))
            w.write("gpmppi/jackal/odom/raw", State(x=p[0], y=p[1], theta=0, v=1.0 if t >= 1 else 0.0, omega=0), ns)
            learned = t >= 20
            names = ["asphalt", "grass", "tile", *(["new-1"] if learned else [])]
            weights = [0.0, 0.1, 0.0, 0.9] if learned else [1.0, 0.0, 0.0]
            w.write("gpmppi/jackal/terrain/weights", TerrainWeights(
                names=names, weights=weights, unknown=0.9 if 11 <= t < 20 else 0.0,
                unknown_channel="one-step" if t >= 11 else ""), ns)
            if i == 200:
                w.write("gpmppi/jackal/model", ModelUpdate(version=1, path="p.npz", sha256="0" * 64, grounds=names,
                                                           learned="new-1", samples=90), ns)
    r = timeline(path)
    assert (r["ground_changed_s"], r["new_ground"], r["first_unknown_over_half_s"]) == (10.0, "sand", 11.0), r
    assert r["unknown_channel"] == "one-step", r
    assert (r["model_update_s"], r["learned"], r["first_weights_naming_it_s"]) == (20.0, "new-1", 20.0), r
    assert r["learned_weight_final"] == 0.9 and r["rmse_before_mm"] == pytest.approx(0.0, abs=0.5), r
    assert r["rmse_new_before_update_mm"] == pytest.approx(20.0, abs=1.0), r
    assert r["rmse_after_update_mm"] == pytest.approx(0.0, abs=0.5), r
