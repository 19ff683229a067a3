"""The calibration drive's excitation and cycle on the physics plant: it stays inside its area, it holds commands
long enough for steady responses, it stops at its target."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from gpmppi.plant.area_excitation import Area, AreaExcitation, predict_path
from gpmppi.plant.calibration_drive import CalibrationDrive, DriveConfig
from gpmppi.plant.excitation import LANE_HOLD_S, LANE_OMEGA, LANE_V, Excitation
from gpmppi.plant.physics import PhysicsPlant
from gpmppi.plant.terrains import load_terrains

DT = 0.1


@pytest.fixture(scope="module")
def terrains():
    return load_terrains()


def closed_loop(terrains, terrain: str, config: DriveConfig, start: np.ndarray, seed: int,
                max_s: float = 3600.0) -> tuple[CalibrationDrive, np.ndarray, np.ndarray]:
    """Drive the plant with the cycle at 10 Hz: (drive, true states, commands). The plant takes each 0.1 s command in
    one call, which runs its internal steps in one compiled loop: the same steps, bit for bit, as ten calls of 0.01 s
    (the digests of `test_without_lane_holds_the_streams_are_as_before` were taken so), at a quarter of the CPU time
    (the Python around each call was 80 % of a drive's)."""
    plant = PhysicsPlant(terrains, terrain, seed=seed, noise=True)
    plant.reset(start)
    drive = CalibrationDrive(config)
    trues, cmds = [plant.state()], []
    k = 0
    while not drive.done and k * DT < max_s:
        cmd = drive.on_state(plant.measure(), k * 100_000_000)
        trues.append(plant.step(cmd, DT))
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
    for share in (-0.1, 1.0, float("nan")):
        with pytest.raises(ValueError, match="lane_holds"):
            DriveConfig(distance_m=10.0, lane_holds=share)


def digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def test_without_lane_holds_the_streams_are_as_before(terrains) -> None:
    """The seeded command streams of main before lane holds came to the drive (sha256 of the float64 bytes): the
    default drive (300 s on the plant, a 20 m and a 6 m area) and the dataset's excitation, plain and with holds."""
    start = np.array([4.0, -3.0, 2.0, 0.0, 0.0])
    for terrain, side, seed, want in [
        ("asphalt", 20.0, 11, "7ca76eaac75e323cffff3d1e0ab7ddc62847ccb46f28835125d9d95a11120eb6"),
        ("grass", 6.0, 12, "8055bfbb2bb89b7202896214fcbf653cd67f18f24101aafe968642ead106a52e"),
    ]:
        _, _, cmds = closed_loop(terrains, terrain, DriveConfig(area_m=side, duration_s=300.0, seed=seed), start, seed)
        assert len(cmds) == 3011 and digest(cmds) == want, terrain
    for share, want in [(0.0, "bcf14e2ac56cf266d8983cd325b47432528fa420c059a55a9d35f86dc5c70767"),
                        (0.15, "e6d9cf9987147ebbb4c93acc3ef0e43ca2bf862691fbf08c33d786063ffe6d32")]:
        exc = Excitation(seed=7, lane_holds=share)
        assert digest(np.vstack([exc.next_segment() for _ in range(300)])) == want, share


def lane_runs(cmds: np.ndarray, v_max: float) -> list[tuple[float, float, float]]:
    """The held runs of a stream at the lane's commands and as long as a lane hold (a turn back's straight run,
    omega exactly 0, is not one)."""
    return [(v, w, s) for v, w, s in held_runs(cmds) if s >= LANE_HOLD_S[0] - 1e-9
            and LANE_V[0] <= v <= min(LANE_V[1], v_max) and 0.0 < abs(w) <= LANE_OMEGA]


@pytest.mark.parametrize(("terrain", "side", "share", "seed"), [("asphalt", 20.0, 0.15, 0), ("grass", 20.0, 0.3, 1),
                                                                ("sand", 10.0, 0.3, 3)])
def test_lane_holds_at_the_asked_share_inside_the_area(terrains, terrain: str, side: float, share: float,
                                                       seed: int) -> None:
    start = np.array([4.0, -3.0, 2.0, 0.0, 0.0])
    config = DriveConfig(area_m=side, duration_s=900.0, seed=seed, lane_holds=share)
    drive, trues, cmds = closed_loop(terrains, terrain, config, start, seed)
    exc, area = drive.excitation, drive.area
    assert exc is not None and area is not None
    assert area.contains(trues[:, :2]), f"left the area: worst offset {np.abs(trues[:, :2] - start[:2]).max():.2f} m"
    # the share of the segments drawn (binomial spread over ~170 segments: 0.03-0.035)
    assert exc.drawn > 120 and abs(exc.lane_held / exc.drawn - share) < 0.08, (exc.lane_held, exc.drawn)
    assert drive.lane_holds == exc.lane_held
    # in the stream: held at the lane's commands for 5 s or more; some are cut short where the robot drifted from
    # its prediction into the margin (the turn back comes at once): 2-4 of 40-50 in 20 m, a third on sand in 10 m
    lane = lane_runs(cmds, config.v_max)
    assert (0.85 if side == 20.0 else 0.6) * exc.lane_held <= len(lane) <= exc.lane_held, (len(lane), exc.lane_held)
    w = np.array([h[1] for h in lane])
    # both ways, and the wide arcs too (in 10 m few of them fit: the holds lean to the tight arcs)
    assert w.min() < -0.3 and w.max() > 0.3 and np.sum(np.abs(w) < 0.3) >= (5 if side == 20.0 else 1)
    assert len(lane_runs(closed_loop(terrains, terrain, config.model_copy(update={"lane_holds": 0.0}), start,
                                     seed)[2], config.v_max)) <= 2  # the plain drive has (nearly) none


def test_a_lane_hold_that_would_leave_is_cut_to_the_part_that_stays_inside() -> None:
    area = Area.square((0.0, 0.0), 20.0)
    exc = AreaExcitation(area, seed=0, lane_holds=0.5)
    pose = np.array([0.0, 0.0, 0.0, 0.0, 0.0])  # at the centre, 8 m to the margin ahead
    straight = np.tile([1.2, 0.01], (80, 1))  # 8 s at 1.2 m/s: 9.6 m
    shortest = int(round(LANE_HOLD_S[0] / DT))
    n = exc._inside_for(pose, straight, shortest)
    assert shortest <= n < 80
    assert area.contains(predict_path(pose, straight[:n], DT), exc.margin)
    assert not area.contains(predict_path(pose, straight[:n + 1], DT), exc.margin)
    # too fast to stay inside for a lane hold's shortest: none
    assert exc._inside_for(pose, np.tile([1.8, 0.0], (80, 1)), shortest) == 0
