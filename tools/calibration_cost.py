"""How long a calibration drive must be for `gpmppi train`'s coverage check to pass, measured on the sim.

`python -m tools.calibration_cost [--grounds tile,asphalt,grass] [--seeds 5] [--minutes 15]` drives the physics plant
on each ground with the calibration drive's own cycle (`CalibrationDrive`, what the calibrate service runs; 10 Hz
states, 100 Hz plant steps, 20 m x 20 m, <= 1.5 m/s) and reports, per ground, the minutes and metres after which the
coverage check passes (default and stricter thresholds), the median over seeds. Offline: no stack, no files."""

from __future__ import annotations

import argparse

import numpy as np

from gpmppi.gp.coverage import MIN_COVERED, MIN_SAMPLES, ground_coverage, held_commands
from gpmppi.models.identify import one_step_pairs
from gpmppi.plant.calibration_drive import CalibrationDrive, DriveConfig
from gpmppi.plant.physics import PhysicsPlant
from gpmppi.plant.terrains import load_terrains

DT = 0.1
# (min samples, min command coverage): the defaults, then stricter targets a user may set with --min-coverage
TARGETS = ((MIN_SAMPLES, MIN_COVERED), (MIN_SAMPLES, 0.5), (MIN_SAMPLES, 0.75), (MIN_SAMPLES, 0.9), (MIN_SAMPLES, 1.0))


def drive_log(terrain: str, seed: int, minutes: float, area: float = 20.0, v_max: float = 1.5) -> dict:
    """Per tick: measured state, command and the distance so far, of one calibration drive on the plant."""
    plant = PhysicsPlant(load_terrains(), terrain, seed=seed, noise=True)
    plant.reset(np.zeros(5))
    drive = CalibrationDrive(DriveConfig(area_m=area, v_max=v_max, duration_s=minutes * 60.0, seed=seed))
    states, cmds, dist = [], [], []
    edge = np.inf  # the true position's closest approach to an edge of the area [m]
    k = 0
    while not drive.reached:
        x = plant.measure()
        cmd = drive.on_state(x, k * 100_000_000)
        states.append(x)
        cmds.append(cmd)
        dist.append(drive.distance)
        for _ in range(10):
            true = plant.step(cmd, 0.01)
            a = drive.area
            assert a is not None
            edge = min(edge, a.half_x - abs(true[0] - a.cx), a.half_y - abs(true[1] - a.cy))
        k += 1
    return {"state": np.array(states), "cmd": np.array(cmds), "dist": np.array(dist), "edge": edge}


def first_pass(log: dict, min_samples: int, min_covered: float, step_s: float = 5.0) -> tuple[float, float] | None:
    """(minutes, metres) after which the coverage check passes, checked every `step_s`; None: not within the log."""
    st, cmd = log["state"], log["cmd"]
    for n in range(int(step_s / DT), len(cmd) + 1, int(step_s / DT)):
        v, w, vr, wr, _, _ = one_step_pairs(st[:n, 3], st[:n, 4], cmd[:n, 0], cmd[:n, 1])
        held = held_commands(cmd[:n, 0], cmd[:n, 1], np.zeros(n), DT)
        cov = ground_coverage("g", np.column_stack([vr, wr, v, w]), held)
        if cov.problem(min_samples, min_covered) is None:
            return n * DT / 60.0, float(log["dist"][n - 1])
    return None


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--grounds", default="tile,asphalt,grass")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--minutes", type=float, default=15.0, help="length of each drive")
    args = parser.parse_args(argv)
    print("| ground | coverage target | minutes (median, max) | metres (median, max) | command cells covered after "
          f"{args.minutes:g} min |")
    print("|---|---|---|---|---|")
    notes = []
    for ground in args.grounds.split(","):
        logs = [drive_log(ground, seed, args.minutes) for seed in range(args.seeds)]
        notes.append(f"{ground}: mean speed {np.mean([lg['dist'][-1] for lg in logs]) / (args.minutes * 60):.2f} m/s, "
                     f"closest to an edge {min(lg['edge'] for lg in logs):.2f} m")
        final = []
        for log in logs:
            v, w, vr, wr, _, _ = one_step_pairs(log["state"][:, 3], log["state"][:, 4], log["cmd"][:, 0],
                                                log["cmd"][:, 1])
            final.append(ground_coverage(ground, np.column_stack([vr, wr, v, w])).command_covered)
        for min_samples, min_covered in TARGETS:
            hits = [first_pass(log, min_samples, min_covered) for log in logs]
            ok = [h for h in hits if h is not None]
            label = f">= {min_samples} samples, >= {min_covered:.0%} of cells"
            if len(ok) < len(hits):
                print(f"| {ground} | {label} | not reached in {len(hits) - len(ok)} of {len(hits)} drives | | |")
                continue
            m = np.array(ok)
            print(f"| {ground} | {label} | {np.median(m[:, 0]):.1f}, {m[:, 0].max():.1f} | "
                  f"{np.median(m[:, 1]):.0f}, {m[:, 1].max():.0f} | {np.median(final):.0%} |")
    print("\n".join(notes))


if __name__ == "__main__":
    main()
