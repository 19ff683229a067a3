"""Bring your own robot (issue 41), end to end: everything the controller learns comes from the robot's own logs.

On a robot the project has not seen (tests/data/light_fast.yaml: 9 kg, stiff fast motors; carpet, dirt, ice): (a)
`gpmppi calibrate drive` through the real stack (its own processes, Zenoh on loopback, the light robot's sim) on
dirt, 12 m; `gpmppi dataset` logs of the same robot on all three grounds (a stack drive runs in real time, and
the terrain calibration needs ~4 minutes of it a ground, 12 settled held commands: too slow for a test, so the
drive's log is pooled with the generator's, as a user's resumed drives are); (b) `gpmppi train` on those logs alone
-> a profile, the drive's log among them; (c) `gpmppi launch` of a launch file whose `profile:` is that file, the
sim on dirt (the ground the stack drove), `--record`; (d) from the recording, read back: the terrain service
identified dirt, the planner published commands, the robot drove the lane and no e-stop was engaged.

The weight bound, checked by hand once (a profile made as here from a 3.5 min drive; 40 s launches; dirt's mean
weight from 3 s to 20 s after the first command): 0.93 with the profile's calibration fitted from the logs; 0.18
with it zeroed (no command-change gains, every ground the grounds' mean steady map and rate, given to the terrain
service as `estimator: {command_gains, response_file}`), carpet then taking 0.75."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner
from zenoh_helpers import REPO, free_port

from gpmppi.plant.excitation import Area
from schemas import BaseCommand, Command, EStop
from services.recording.mcap_io import read_messages
from tools.cli import app
from tools.dataset import read_dataset

runner = CliRunner()
LIGHT = REPO / "tests" / "data" / "light_fast.yaml"
ROBOT = "light"
DRIVEN = "dirt"  # the ground the stack drives, then launches on
DRIVE_M = 12.0  # the route, not the whole calibration: 12 settled holds a ground took 3.5-4 min of driving
AREA_M = 10.0
OTHERS_M = 600.0  # metres a ground of `gpmppi dataset` (300 m held 11 settled holds on ice)
LAUNCH_S = 20.0
# dirt's mean weight from 3 s after the first command: 0.95 on a quiet machine, 0.66 once beside a full suite on 2
# cores (its states then reach the terrain service late); 0.18 with the calibration zeroed (the docstring)
IDENTIFIED = 0.5


def launch_file(folder: Path, **top: object) -> Path:
    """The light robot's stack on loopback (no warm spares: not what this checks, a third of a stack's CPU). Without
    a profile (the calibration drive, whose planner `calibrate drive` replaces) no terrain service either: nothing
    of it is calibrated yet, and the drive records no weights."""
    path = folder / f"light{'-profile' if top else ''}.yaml"
    terrain = [{"name": "terrain", "required": False, "config": {"base_period_s": 0.01}}] if top else []
    path.write_text(yaml.safe_dump({
        "robot": ROBOT, **top, "spares": [],
        "services": [
            {"name": "sim", "config": {"terrain": DRIVEN, "lane": "circle", "publish_hz": 10.0,
                                       "terrain_file": str(LIGHT)}},
            {"name": "ingress", "config": {"source": "sim"}},
            *terrain,
            {"name": "planner", "config": {"scenario": "circle", "trigger": "state"}},
            {"name": "egress", "config": {"output": "sim"}},
        ],
    }))
    return path


@pytest.mark.slow(seconds=75)  # a 12 m stack drive, the fit, a 20 s launch (its stack started twice)
@pytest.mark.exclusive  # two real-time stacks: ahead of the others for the CPU, as the other stack tests
@pytest.mark.timeout(900)
def test_a_new_robot_is_driven_trained_and_launched_from_its_own_logs(tmp_path: Path) -> None:
    from tools.stack_terrain import load

    stack = launch_file(tmp_path)
    # (a) the calibration drive through the stack on dirt; every ground from the dataset generator too
    rec = tmp_path / "calib"
    drove = runner.invoke(app, ["calibrate", "drive", "--ground", DRIVEN, "--distance", str(DRIVE_M),
                                "--area", str(AREA_M), "--record", str(rec), "--launch-file", str(stack),
                                "--port", str(free_port())])
    assert drove.exit_code == 0, drove.output[-3000:]
    assert f"{DRIVEN} in {rec}: 1" in " ".join(drove.output.split())  # the total driven, said at the end
    drive_logs = sorted(rec.glob("*.mcap"))
    assert len(drive_logs) == 1 and drive_logs[0].name.startswith(f"calib-{DRIVEN}-"), drive_logs
    # what the drive adds to the fit, read as `gpmppi train` reads it: dirt only, commands paired on 0.1 s ticks
    driven = read_dataset(drive_logs[0], robot=ROBOT)
    assert set(driven) == {DRIVEN}, set(driven)
    assert sum(len(r.time) for r in driven[DRIVEN]) > 100, [len(r.time) for r in driven[DRIVEN]]
    assert DRIVE_M - 1.0 < sum(r.distance for r in driven[DRIVEN]) < DRIVE_M + 4.0
    for r in driven[DRIVEN]:
        assert np.all(np.abs(np.diff(r.time) - 0.1) <= 0.025)
    states = np.concatenate([r.state for r in driven[DRIVEN]])
    assert Area.square(states[0, :2], AREA_M).contains(states[:, :2], -0.2)  # inside the area (0.2 m: sensor noise)
    # what the base got went through egress (its limits, watchdog and e-stop), following the drive's commands
    keys = {f"gpmppi/{ROBOT}/base/cmd": "base", f"gpmppi/{ROBOT}/cmd": "cmd"}
    sent = [(keys[k], m) for k, _, m in read_messages(drive_logs[0], keys=keys)]
    assert {m.reason for k, m in sent if k == "base"} <= {"planner", "limit", "watchdog"}
    assert any(isinstance(m, Command) and m.v_ref > 0.2 for _, m in sent)
    others = tmp_path / "others.mcap"
    made = runner.invoke(app, ["dataset", "-o", str(others), "--terrain-file", str(LIGHT), "-t", "carpet", "-t",
                               DRIVEN, "-t", "ice", "--distance", str(OTHERS_M), "--robot", ROBOT, "--seed", "1"])
    assert made.exit_code == 0, made.output[-3000:]
    # (b) one profile from those logs alone
    profile = tmp_path / "robot.npz"
    trained = runner.invoke(app, ["train", *map(str, drive_logs), str(others), "-o", str(profile),
                                  "--robot", ROBOT, "--points", "120", "--iters", "60", "--grid-nodes", "12"])
    assert trained.exit_code == 0, trained.output[-3000:]
    # (c) the launch file names it once; the sim drives dirt
    run = tmp_path / "run.mcap"
    launched = runner.invoke(app, ["launch", str(launch_file(tmp_path, profile=str(profile))), "--duration",
                                   str(LAUNCH_S), "--record", str(run), "--port", str(free_port())])
    assert launched.exit_code == 0, launched.output[-3000:]
    # (d) the recording: commands published, the robot drove, no e-stop, and dirt identified
    keys = {f"gpmppi/{ROBOT}/{k}": k for k in ("cmd", "base/cmd", "estop")}
    msgs = [(keys[k], m) for k, _, m in read_messages(run, keys=keys)]
    cmds = [m for k, m in msgs if isinstance(m, Command)]
    assert len(cmds) > 100 and max(c.v_ref for c in cmds) > 0.5, len(cmds)
    assert not [m for k, m in msgs if isinstance(m, EStop) and m.engaged]
    assert {m.reason for k, m in msgs if isinstance(m, BaseCommand)} <= {"planner", "limit", "watchdog"}
    log = load(run)
    xy = np.array([s[:2] for _, _, s in log["states"]])
    assert np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1)) > 10.0
    # the weights from 3 s after the planner's first command (before it the robot waits, and standing still is no
    # evidence of any ground), one a state, in the profile's ground order
    names = ["carpet", "dirt", "ice"]
    start = min(c.header.stamp_ns for c in cmds) + 3_000_000_000
    w = np.array([[ws[n] for n in names] for stamp, ws in sorted(log["weights"], key=lambda sw: sw[0])
                  if stamp >= start])
    assert len(w) > 100, len(w)
    mean = w.mean(axis=0)
    print(f"\nweights (carpet, dirt, ice) from 3 s after the first command: mean {mean.round(3)}, dirt on top "
          f"{np.mean(np.argmax(w, axis=1) == 1):.0%} of the time")
    assert int(np.argmax(mean)) == names.index(DRIVEN) and mean[names.index(DRIVEN)] >= IDENTIFIED, mean
