"""`gpmppi bench startup`'s kill rounds (`tools/bench_startup.py`): each service killed with SIGKILL while the robot
drives, once its warm spare is ready, and what followed (`Takeover`): kill -> the new process's first output at the
outside client, the dead process's last output -> that, and for the planner the base's first zero after the dead
planner's last command, driving again after it, and the lane RMSE over the 5 s after the takeover against the 5 s
before the kill (`no_kill_reference`: the same ratio away from every kill).
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from gpmppi.tasks import TaskOutline
from schemas import Task
from services.launch.monitor import PRIMARY_OUTPUT, Monitor
from services.launch.processes import Child
from services.launch.supervisor import Launcher
from tools.lane_windows import consecutive_window_ratios, ratio_summary

MOVING = 0.05  # [m/s] a base command above this is driving
RMSE_WINDOW_S = 5.0


@dataclass
class Takeover:
    """One SIGKILL of one service while the robot drives, and what followed."""

    service: str
    old_pid: int
    pid: int | None  # the process that took the role (None: none within the timeout)
    by_spare: bool  # a warm spare took over (else a new process was started)
    spare_ready_s: float | None  # that spare's process start -> ready (loaded, waiting)
    kill_to_output_s: float | None  # SIGKILL -> the new process's first output at the outside client
    gap_s: float | None  # the dead process's last output -> the new process's first output
    zero_after_last_cmd_s: float | None  # planner: its last command -> the base's first zero (None: no zero)
    driving_after_last_cmd_s: float | None  # the last planner command before the kill -> a moving base command
    rmse_before_mm: float | None  # lane RMSE over the 5 s before the kill
    rmse_after_mm: float | None  # ... over the 5 s after the new process's first output
    load_avg_1min: float
    kill_ns: int = 0  # when the SIGKILL was sent, by the wall clock the states are stamped with [ns]
    first_output_ns: int | None = None  # the new process's first output at the outside client, same clock [ns]


def kill_rounds(
    services: list[str], kills: int, settle_s: float, timeout_s: float, records: list[Takeover],
    jitter_s: float = 0.0, seed: int = 0,
) -> Callable[[Launcher, Monitor], None]:
    """A `then` hook: SIGKILL each service `kills` times while the robot drives, each once its spare is ready and
    its process has run `restart_reset_s` (an earlier death is then not "in a row", which a takeover requires), and
    a further random 0-`jitter_s` (seeded): a planner killed always after the same time is killed always at the same
    plan count, so at the same place in its seeded noise, and its kills repeat one draw rather than sample many."""
    rng = np.random.default_rng(seed)

    def kill_each_service(launcher: Launcher, monitor: Monitor) -> None:
        for _ in range(kills):
            for name in services:
                child = launcher.child(name)
                ready = _wait_ready_to_kill(launcher, monitor, child, timeout_s)
                if ready and jitter_s > 0:
                    if launcher.stop_event.wait(float(rng.uniform(0.0, jitter_s))):
                        return
                    ready = _wait_ready_to_kill(launcher, monitor, child, timeout_s)
                if not ready:
                    if launcher.stop_event.is_set():
                        return
                    launcher.say("bench", f"{name}: no spare ready or not driving within {timeout_s:.0f} s; "
                                          "killing anyway")
                record = _kill_once(launcher, monitor, child, timeout_s)
                records.append(record)
                launcher.say("bench", f"killed {name}: {asdict(record)}")
                if launcher.stop_event.wait(max(settle_s, RMSE_WINDOW_S + 0.5)):
                    return

    return kill_each_service


def _driving(monitor: Monitor, steady_s: float = 1.0, max_gap_s: float = 0.25) -> bool:
    """The planner's commands arrived for the last `steady_s` with no gap over `max_gap_s`, and the base follows."""
    now = time.monotonic()
    key = f"gpmppi/{monitor.robot}/cmd"
    with monitor.lock:
        cmds = [t for t, _ in monitor.output_arrivals[key] if t >= now - steady_s - max_gap_s]
        base = [b for b in monitor.base_commands if b[0] >= now - max_gap_s]
    if not cmds or cmds[0] > now - steady_s or now - cmds[-1] > max_gap_s:
        return False
    if any(b - a > max_gap_s for a, b in zip(cmds, cmds[1:], strict=False)):
        return False
    return bool(base) and base[-1][3] in ("planner", "limit", "ramp") and base[-1][1] > MOVING


def _wait_ready_to_kill(launcher: Launcher, monitor: Monitor, child: Child, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s + launcher.launch.restart_reset_s
    while time.monotonic() < deadline:
        spare = child.spare
        # a death within restart_reset_s of the last one is "in a row": a restart with backoff, not a takeover
        settled = time.monotonic() - child.started_at >= launcher.launch.restart_reset_s
        spare_ready = not launcher.wants_spare(child) or (spare is not None and spare.ready_at is not None)
        if spare_ready and settled and _driving(monitor):
            return True
        if launcher.stop_event.wait(0.1):
            return False
    return False


def _kill_once(launcher: Launcher, monitor: Monitor, child: Child, timeout_s: float) -> Takeover:
    key = f"gpmppi/{monitor.robot}/{PRIMARY_OUTPUT[child.kind]}"
    cmd_key = f"gpmppi/{monitor.robot}/cmd"
    spare = child.spare
    spare_ready = None if spare is None or spare.ready_at is None else round(spare.ready_at - spare.started_at, 3)
    load = round(os.getloadavg()[0], 2)
    old_pid = child.process.pid if child.process is not None else -1
    t_kill = time.monotonic()
    kill_ns = time.time_ns()
    with monitor.lock:
        before = [seq for t, seq in monitor.output_arrivals[key] if t < t_kill]
    old_last = before[-1] if before else None
    launcher.kill(child.name, signal.SIGKILL)
    first = first_output(launcher, monitor, key, t_kill, old_last, timeout_s)
    new_pid = child.process.pid if child.process is not None and child.process.pid != old_pid else None
    by_spare = any(e.takeover_pid == new_pid for e in launcher.restart_events) if new_pid else False
    gap = zero = driving = rmse_before = rmse_after = None
    if first is not None:
        with monitor.lock:
            old_outputs = [t for t, _ in monitor.output_arrivals[key] if t < first[0]]
        gap = round(first[0] - old_outputs[-1], 3) if old_outputs else None
        # what the base did: wait for the RMSE window after the takeover
        launcher.stop_event.wait(max(0.0, first[0] + RMSE_WINDOW_S + 0.3 - time.monotonic()))
        with monitor.lock:
            cmds = [t for t, _ in monitor.output_arrivals[cmd_key]]
            base = list(monitor.base_commands)
            states = sorted(monitor.states)
            task = monitor.task
        last_cmd = max((t for t in cmds if t < t_kill), default=None)
        if child.kind == "planner":
            last_cmd = max((t for t in cmds if t < first[0]), default=None)  # the dead planner's last
        if last_cmd is not None:
            # (egress repeats the last command until its watchdog fires: driving again counts from the new output)
            back = next((t for t, v, _, r in base if t >= first[0] and r in ("planner", "limit", "ramp")
                         and v > MOVING), None)
            zero_t = next((t for t, v, w, _ in base if t > last_cmd and v == 0.0 and w == 0.0
                           and (back is None or t < back)), None)
            zero = None if zero_t is None else round(zero_t - last_cmd, 3)
            driving = None if back is None else round(back - last_cmd, 3)
        first_ns = kill_ns + int((first[0] - t_kill) * 1e9)
        rmse_before = _lane_rmse(states, task, kill_ns - int(RMSE_WINDOW_S * 1e9), kill_ns)
        rmse_after = _lane_rmse(states, task, first_ns, first_ns + int(RMSE_WINDOW_S * 1e9))
    return Takeover(
        service=child.name, old_pid=old_pid, pid=new_pid, by_spare=by_spare, spare_ready_s=spare_ready,
        kill_to_output_s=None if first is None else round(first[0] - t_kill, 3), gap_s=gap,
        zero_after_last_cmd_s=zero, driving_after_last_cmd_s=driving, rmse_before_mm=rmse_before,
        rmse_after_mm=rmse_after, load_avg_1min=load, kill_ns=kill_ns,
        first_output_ns=None if first is None else kill_ns + int((first[0] - t_kill) * 1e9),
    )


def _lane_rmse(states: list[tuple[int, float, float]], task: Task | None, t0_ns: int, t1_ns: int) -> float | None:
    lane = _lane(task)
    if lane is None:
        return None
    from gpmppi.evaluation import metrics

    xy = np.array([[x, y] for stamp, x, y in states if t0_ns <= stamp < t1_ns]).reshape(-1, 2)
    if xy.shape[0] < 5:
        return None
    return round(metrics.lane_rmse_mm(xy, lane.lane, lane.closed), 1)


def _lane(task: Task | None) -> TaskOutline | None:
    """The task's outline where it has a lane to measure the RMSE to (its kind's `outline`), else None."""
    if task is None:
        return None
    from services.codec.convert import task_from_message

    outline = task_from_message(task).outline()
    return outline if outline.lane is not None else None


def no_kill_reference(monitor: Monitor, takeovers: list[Takeover], begin_ns: int) -> dict[str, float | int | None]:
    """The after / before RMSE ratio of consecutive windows over the kill rounds' states, away from every kill
    (from RMSE_WINDOW_S before it to RMSE_WINDOW_S after the new process's first output)."""
    with monitor.lock:
        states = [s for s in monitor.states if s[0] >= begin_ns]
        task = monitor.task
    lane = _lane(task)
    if lane is None or not states:
        return {}
    w = int(RMSE_WINDOW_S * 1e9)
    excluded = [(t.kill_ns - w, (t.first_output_ns or t.kill_ns) + w) for t in takeovers]
    stamps = np.array([s[0] for s in states])
    xy = np.array([[x, y] for _, x, y in states])
    ratios = consecutive_window_ratios(stamps, xy, lane.lane, lane.closed, excluded, RMSE_WINDOW_S)
    return ratio_summary(ratios)


def first_output(
    launcher: Launcher, monitor: Monitor, key: str, started: float, old_last: int | None, timeout_s: float
) -> tuple[float, int] | None:
    """(arrival time, seq) of the new process's first output on `key`, or None after `timeout_s`."""
    deadline = started + timeout_s
    while time.monotonic() < deadline and not launcher.stop_event.is_set():
        with monitor.lock:
            arrivals = [(t, seq) for t, seq in monitor.output_arrivals[key] if t >= started]
        for t, seq in arrivals:
            if old_last is None or seq <= old_last:
                return t, seq
        time.sleep(0.005)  # the arrival time is taken on receipt: this poll does not add to it
    return None
