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
            # drive straight at 1 m/s (20 Hz, as egress sends) until well after the switch
            end = time.monotonic() + SWITCH_S + 2.5
            while time.monotonic() < end:
                pub.put(encode(BaseCommand(v=1.0, omega=0.0, header=Header(stamp_ns=time.time_ns()))))
                time.sleep(0.05)
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
