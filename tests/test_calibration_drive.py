"""The calibration drive's excitation and cycle on the physics plant: it stays inside its area, it holds commands
long enough for steady responses, it stops at its target."""

from __future__ import annotations

import numpy as np
import pytest

from gpmppi.plant.calibration_drive import CalibrationDrive, DriveConfig
from gpmppi.plant.excitation import Area, AreaExcitation, predict_path
from gpmppi.plant.physics import PhysicsPlant
from gpmppi.plant.terrains import load_terrains

DT = 0.1


@pytest.fixture(scope="module")
def terrains():
    return load_terrains()


def closed_loop(terrains, terrain: str, config: DriveConfig, start: np.ndarray, seed: int,
                max_s: float = 3600.0) -> tuple[CalibrationDrive, np.ndarray, np.ndarray]:
    """Drive the plant with the cycle at 10 Hz (the plant steps at 100 Hz): (drive, true states, commands)."""
    plant = PhysicsPlant(terrains, terrain, seed=seed, noise=True)
    plant.reset(start)
    drive = CalibrationDrive(config)
    trues, cmds = [plant.state()], []
    k = 0
    while not drive.done and k * DT < max_s:
        cmd = drive.on_state(plant.measure(), k * 100_000_000)
        for _ in range(10):
            true = plant.step(cmd, 0.01)
        trues.append(true)
        cmds.append(cmd)
        k += 1
    return drive, np.array(trues), np.array(cmds)


def held_runs(cmds: np.ndarray) -> list[tuple[float, float, float]]:
    """(v, omega, seconds) of each run of one unchanged command."""
    out = []
    start = 0
    for i in range(1, len(cmds) + 1):
        if i == len(cmds) or np.any(np.abs(cmds[i] - cmds[start]) > 1e-9):
            out.append((float(cmds[start, 0]), float(cmds[start, 1]), (i - start) * DT))
            start = i
    return out


@pytest.mark.parametrize(("terrain", "side", "seed"), [("asphalt", 20.0, 0), ("grass", 20.0, 1), ("sand", 20.0, 2),
                                                       ("tile", 6.0, 3), ("sand", 6.0, 4)])
def test_the_robot_never_leaves_the_area(terrains, terrain: str, side: float, seed: int) -> None:
    start = np.array([4.0, -3.0, 2.0, 0.0, 0.0])
    drive, trues, cmds = closed_loop(terrains, terrain, DriveConfig(area_m=side, duration_s=600.0, seed=seed), start,
                                     seed)
    area = drive.area
    assert area is not None and (area.cx, area.cy) == pytest.approx((4.0, -3.0), abs=0.1)  # centred on the start
    assert area.contains(trues[:, :2]), f"left the area: worst offset {np.abs(trues[:, :2] - start[:2]).max():.2f} m"
    # and it did drive: it is not inside because it stood still
    assert drive.distance > (100.0 if side == 20.0 else 50.0)
    assert np.abs(trues[:, :2] - start[:2]).max() > 0.3 * side


def test_held_commands_of_two_to_five_seconds_across_speeds_and_turn_rates(terrains) -> None:
    drive, _, cmds = closed_loop(terrains, "asphalt", DriveConfig(duration_s=900.0, seed=5), np.zeros(5), 5)
    assert np.all(cmds[:, 0] >= 0.0) and np.all(cmds[:, 0] <= 1.5 + 1e-12)  # the speed cap
    held = [(v, w, s) for v, w, s in held_runs(cmds) if 2.0 - 1e-9 <= s <= 5.0 + 1e-9]
    # 900 s of driving: about a third of the segments are holds of 2-5 s (turns back add more)
    assert len(held) >= 40, len(held)
    v = np.array([h[0] for h in held])
    w = np.array([h[1] for h in held])
    assert v.min() < 0.5 and v.max() > 1.2  # the speeds 0-1.5 m/s
    assert w.min() < -1.0 and w.max() > 1.0 and np.sum(np.abs(w) < 0.5) >= 3  # both ways, and straight
    assert np.sum([h[2] for h in held]) > 0.25 * len(cmds) * 0.1  # a good share of the time is held


def test_the_drive_stops_at_its_distance_and_commands_zero(terrains) -> None:
    drive, trues, cmds = closed_loop(terrains, "tile", DriveConfig(distance_m=60.0, seed=6), np.zeros(5), 6)
    assert drive.done and 60.0 <= drive.distance < 63.0
    assert np.all(cmds[-9:] == 0.0)  # stop_s of zero at the end
    assert abs(trues[-1, 3]) < 0.1  # braked to (nearly) rest on the record


def test_same_seed_same_commands() -> None:
    area = Area.square((0.0, 0.0), 20.0)
    pose = np.array([1.0, 2.0, 0.3, 0.5, 0.0])
    a, b = AreaExcitation(area, seed=7), AreaExcitation(area, seed=7)
    for _ in range(20):
        sa, sb = a.next_segment(pose), b.next_segment(pose)
        assert np.array_equal(sa, sb)
    other = AreaExcitation(area, seed=8).next_segment(pose)
    assert not np.array_equal(other, AreaExcitation(area, seed=7).next_segment(pose))


def test_a_robot_at_the_edge_heading_out_turns_back() -> None:
    area = Area.square((0.0, 0.0), 20.0)
    exc = AreaExcitation(area, seed=0)
    pose = np.array([9.0, 0.0, 0.0, 1.0, 0.0])  # in the margin, facing out
    assert exc.heading_out(pose)
    seg = exc.next_segment(pose)
    assert exc.returns == 1
    path = predict_path(pose, seg, DT)
    assert area.contains(path) and path[-1, 0] < 8.0  # it came back in


def test_bad_areas_and_targets_are_refused() -> None:
    with pytest.raises(ValueError, match="at least 6 m"):
        AreaExcitation(Area.square((0, 0), 4.0))
    with pytest.raises(ValueError, match="target"):
        DriveConfig()
    with pytest.raises(ValueError, match="area_m"):
        DriveConfig(area_m=3.0, distance_m=10.0)
