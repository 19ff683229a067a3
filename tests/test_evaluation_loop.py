"""Closed-loop mechanics with hand-made stand-ins: plant rate, latency, terrain switches, stops, determinism."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from gpmppi.evaluation.closed_loop import ClosedLoopConfig, latency_from_cycles, run_closed_loop
from gpmppi.tasks import GoalTask, LaneTask


class KinematicPlant:
    """Integrates a kinematic unicycle at its own step and logs every command it received, with time."""

    def __init__(self, dt: float = 0.02, noise: float = 0.0, seed: int = 0) -> None:
        self.dt = dt
        self.rng = np.random.default_rng(seed)
        self.noise = noise
        self.t = 0.0
        self.log: list[tuple[float, float]] = []  # (time, v_ref) at each internal step
        self.terrain_log: list[tuple[float, str]] = []

    def reset(self, state: np.ndarray) -> None:
        self.x = np.asarray(state, float).copy()
        self.t = 0.0

    def set_terrain(self, name: str) -> None:
        self.terrain_log.append((self.t, name))

    def step(self, command: np.ndarray, duration: float) -> np.ndarray:
        n = max(1, round(duration / self.dt))
        h = duration / n
        for _ in range(n):
            self.log.append((self.t, float(command[0])))
            self.x[3], self.x[4] = command
            self.x[0] += self.x[3] * np.cos(self.x[2]) * h
            self.x[1] += self.x[3] * np.sin(self.x[2]) * h
            self.x[2] += self.x[4] * h
            self.t += h
        return self.x.copy()

    def measure(self) -> np.ndarray:
        return self.x + self.noise * self.rng.standard_normal(5)


@dataclass
class Result:
    control: np.ndarray
    tightened: np.ndarray
    states: np.ndarray
    effective_samples: float = 1.0


class CountingPlanner:
    """Commands v = 1 + 0.1 k (so each cycle's command is recognisable) straight ahead; records weights seen."""

    def __init__(self) -> None:
        self.k = 0
        self.weights_seen: list[np.ndarray] = []
        self.delays: list[float] = []

    def reset(self) -> None:
        self.k = 0

    def prepare(self, weights) -> None:
        pass

    def plan(self, state, task, weights=None, state_cov=None, delay_s: float = 0.0) -> Result:
        self.weights_seen.append(np.asarray(weights).copy())
        self.delays.append(delay_s)
        u = np.array([1.0 + 0.1 * self.k, 0.0])
        self.k += 1
        return Result(u, np.full(3, 1.0), np.zeros((3, 5)))


@dataclass
class Estimate:
    weights: np.ndarray
    ok: bool = True
    residual: float = 0.0
    message: str = ""


class RecordingEstimator:
    def __init__(self) -> None:
        self.seen: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def observe(self, state, command, next_state) -> None:
        self.seen.append((state.copy(), command.copy(), next_state.copy()))

    def estimate(self) -> Estimate:
        return Estimate(np.array([0.2, 0.8]))


LANE = LaneTask(np.array([[0.0, 0.0], [100.0, 0.0]]), half_width=1.0, closed=False)


def test_no_latency_applies_each_command_over_its_cycle() -> None:
    plant = KinematicPlant(dt=0.02)
    traj = run_closed_loop(CountingPlanner(), plant, LANE, np.zeros(5), 2, ClosedLoopConfig(time_limit_s=0.5))
    assert traj.status == "time_limit" and traj.commands.shape == (5, 2)
    np.testing.assert_allclose(traj.times, np.arange(6) * 0.1)
    assert len(plant.log) == 25  # the plant ran at its own 0.02 s step
    # x after 5 cycles = 0.1 * (1.0 + 1.1 + 1.2 + 1.3 + 1.4)
    assert traj.true_states[-1, 0] == pytest.approx(0.6)


def test_latency_of_one_cycle_delays_commands() -> None:
    plant = KinematicPlant(dt=0.02)
    cfg = ClosedLoopConfig(time_limit_s=0.5, latency_s=latency_from_cycles(1))
    traj = run_closed_loop(CountingPlanner(), plant, LANE, np.zeros(5), 2, cfg)
    # first cycle applies zero (nothing has arrived), then the previous cycle's command
    assert traj.true_states[-1, 0] == pytest.approx(0.1 * (0.0 + 1.0 + 1.1 + 1.2 + 1.3))


def test_fractional_latency_switches_inside_a_cycle() -> None:
    plant = KinematicPlant(dt=0.01)
    cfg = ClosedLoopConfig(time_limit_s=0.3, latency_s=0.05)
    planner = CountingPlanner()
    run_closed_loop(planner, plant, LANE, np.zeros(5), 2, cfg)
    assert planner.delays == [0.05] * 3  # the planner is told the latency its commands will meet
    uncompensated = CountingPlanner()
    run_closed_loop(uncompensated, KinematicPlant(dt=0.01), LANE, np.zeros(5), 2,
                    ClosedLoopConfig(time_limit_s=0.3, latency_s=0.05, compensate_latency=False))
    assert uncompensated.delays == [0.0] * 3
    v_at = {round(t, 3): v for t, v in plant.log}
    assert v_at[0.04] == 0.0 and v_at[0.05] == 1.0 and v_at[0.14] == 1.0 and v_at[0.15] == pytest.approx(1.1)


def test_estimator_sees_measured_transitions_and_feeds_weights() -> None:
    est = RecordingEstimator()
    planner = CountingPlanner()
    traj = run_closed_loop(planner, KinematicPlant(), LANE, np.zeros(5), 2, ClosedLoopConfig(time_limit_s=0.4),
                           estimator=est)
    assert len(est.seen) == 3  # cycles 1..3 observe the transitions of cycles 0..2
    for k, (s, u, s_next) in enumerate(est.seen):
        np.testing.assert_array_equal(s, traj.measured_states[k])
        np.testing.assert_array_equal(u, traj.commands[k])
        np.testing.assert_array_equal(s_next, traj.measured_states[k + 1])
    np.testing.assert_allclose(planner.weights_seen[0], [0.5, 0.5])
    np.testing.assert_allclose(planner.weights_seen[1], [0.2, 0.8])
    assert traj.weights_ok.tolist() == [False, True, True, True]


def test_terrain_switch_and_distance_stop() -> None:
    plant = KinematicPlant()
    cfg = ClosedLoopConfig(time_limit_s=10.0, distance_limit_m=2.0, terrain_switches=((0.5, "sand"),))
    traj = run_closed_loop(CountingPlanner(), plant, LANE, np.zeros(5), 2, cfg, initial_terrain="grass")
    assert traj.status == "distance"
    assert [n for _, n in plant.terrain_log] == ["grass", "sand"]
    assert plant.terrain_log[1][0] == pytest.approx(0.5)
    assert traj.terrains[4] == "grass" and traj.terrains[5] == "sand"
    # the run stops at the first cycle whose cumulative distance 0.1 * sum(1 + 0.1 k) reaches 2 m
    driven = np.cumsum(0.1 * (1.0 + 0.1 * np.arange(20)))
    assert len(traj.commands) == int(np.argmax(driven >= 2.0 - 1e-9)) + 1


def test_goal_and_collision_stops() -> None:
    goal = GoalTask(goal=np.array([1.0, 0.0]), tolerance=0.2)
    traj = run_closed_loop(CountingPlanner(), KinematicPlant(), goal, np.zeros(5), 2, ClosedLoopConfig())
    assert traj.status == "goal" and np.linalg.norm(traj.positions[-1] - goal.goal) <= 0.2
    wall = GoalTask(goal=np.array([5.0, 0.0]), tolerance=0.2, obstacles=np.array([[2.0, 0.0, 0.5]]))
    traj = run_closed_loop(CountingPlanner(), KinematicPlant(), wall, np.zeros(5), 2, ClosedLoopConfig())
    assert traj.status == "collision" and traj.positions[-1, 0] >= 1.5


def test_same_seed_same_run_and_noise_reaches_planner_only_through_measurements() -> None:
    runs = [
        run_closed_loop(CountingPlanner(), KinematicPlant(noise=0.01, seed=s), LANE, np.zeros(5), 2,
                        ClosedLoopConfig(time_limit_s=0.5))
        for s in (3, 3, 4)
    ]
    np.testing.assert_array_equal(runs[0].measured_states, runs[1].measured_states)
    assert not np.array_equal(runs[0].measured_states, runs[2].measured_states)
    np.testing.assert_array_equal(runs[0].true_states, runs[2].true_states)  # this planner ignores the state


def test_plant_failure_ends_the_run_with_a_status() -> None:
    class FailingPlant(KinematicPlant):
        def step(self, command: np.ndarray, duration: float) -> np.ndarray:
            if self.t > 0.25:
                raise FloatingPointError("diverged")
            return super().step(command, duration)

    traj = run_closed_loop(CountingPlanner(), FailingPlant(), LANE, np.zeros(5), 2, ClosedLoopConfig(time_limit_s=1.0))
    assert traj.status == "plant_error" and "diverged" in traj.message
    assert len(traj.commands) == len(traj.times) - 1 == 3


class StopAtPlanner:
    """Straight ahead at 1 m/s until x reaches `stop_x`, then stands still (as a planner at a lane's end)."""

    def __init__(self, stop_x: float) -> None:
        self.stop_x = stop_x

    def reset(self) -> None:
        pass

    def prepare(self, weights) -> None:
        pass

    def plan(self, state, task, weights=None, state_cov=None, delay_s: float = 0.0) -> Result:
        v = 1.0 if state[0] < self.stop_x - 1e-9 else 0.0
        return Result(np.array([v, 0.0]), np.full(3, 1.0), np.zeros((3, 5)))


SHORT_LANE = LaneTask(np.array([[0.0, 0.0], [10.0, 0.0]]), half_width=1.0, closed=False)


def test_open_lane_finishes_at_its_end_and_scores_the_driven_part_only() -> None:
    from gpmppi.evaluation.runner import score

    start = np.array([0.0, 0.1, 0.0, 0.0, 0.0])  # 100 mm beside the centre line, all along
    cfg = ClosedLoopConfig(time_limit_s=20.0, lane_end_tolerance_m=0.45)  # not a whole cycle's way (0.1 m)
    traj = run_closed_loop(StopAtPlanner(9.8), KinematicPlant(), SHORT_LANE, start, 2, cfg)
    # 1 m/s: within 0.45 m of the end (x >= 9.55) after 96 cycles
    assert traj.status == "finished" and len(traj.commands) == 96
    assert traj.times[-1] == pytest.approx(9.6) and traj.positions[-1, 0] == pytest.approx(9.6)
    s = score(traj, SHORT_LANE, 0, cfg)
    assert s.success and s.mean_speed_mps == pytest.approx(1.0) and s.rmse_mm == pytest.approx(100.0)
    assert s.v_ref_rate_mean == 0.0 and s.v_ref_rate_p95 == 0.0  # one steady command: no change
    assert s.true_weight_mean is None and s.weight_switches_per_min is None  # not an adapting model

    # the old rule: the run waits at x = 9.8 until the time limit, and its mean speed counts the wait
    old = ClosedLoopConfig(time_limit_s=20.0, stop_at_lane_end=False)
    waited = run_closed_loop(StopAtPlanner(9.8), KinematicPlant(), SHORT_LANE, start, 2, old)
    assert waited.status == "time_limit" and waited.times[-1] == pytest.approx(20.0)
    w = score(waited, SHORT_LANE, 0, old)
    assert w.mean_speed_mps == pytest.approx(9.8 / 20.0) and not w.success
    # stopping from 1 m/s in one cycle: one v_ref change of 10 m/s^2 among 199
    assert w.v_ref_rate_mean == pytest.approx(10.0 / 199)


def test_closed_lanes_and_lanes_ending_at_their_start_do_not_finish_early() -> None:
    closed = LaneTask(SHORT_LANE.centerline, half_width=1.0, closed=True)
    traj = run_closed_loop(StopAtPlanner(9.8), KinematicPlant(), closed, np.zeros(5), 2,
                           ClosedLoopConfig(time_limit_s=12.0))
    assert traj.status == "time_limit"
    # an open U whose end (0, 0.5) lies beside its start: starting there is not arriving (less than half driven)
    u_lane = LaneTask(np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 4.0], [0.0, 4.0], [0.0, 0.5]]), half_width=1.0,
                      closed=False)
    start = np.array([0.0, 0.3, 0.0, 0.0, 0.0])
    from gpmppi.evaluation.metrics import lane_end_reached

    assert lane_end_reached(start[None, :2], u_lane.centerline, 1.0)[0]
    traj = run_closed_loop(StopAtPlanner(5.0), KinematicPlant(), u_lane, start, 2, ClosedLoopConfig(time_limit_s=3.0))
    assert traj.status == "time_limit"


def test_lane_end_tolerance_must_not_be_negative() -> None:
    with pytest.raises(ValueError, match="lane_end_tolerance_m"):
        ClosedLoopConfig(lane_end_tolerance_m=-0.1)
