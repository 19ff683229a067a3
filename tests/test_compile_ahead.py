"""The rollout kernel compiled ahead in a second process on a cold cache (`gpmppi.mppi.compile_ahead`): when it is
not started, and what the plan does when the child cannot help. That the plans are the same either way, and that
the child's kernel is the one the plan loads, is `tests/test_determinism.py`'s (it compiles histories both ways)."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from cached_models import synthetic_model

from gpmppi.mppi import compile_ahead
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.scenarios import circle_lane


def test_not_started_when_turned_off_or_the_kernel_is_cached(monkeypatch: pytest.MonkeyPatch) -> None:
    sc = circle_lane()
    Planner(PlannerConfig(samples=32, horizon=8), synthetic_model(nodes=4, n_train=20)).plan(sc.start, sc.task)
    assert compile_ahead.rollout_kernel_cached()  # compiled or loaded by the plan above
    assert compile_ahead.start(()) is None  # so nothing is started, whatever the arguments
    monkeypatch.setenv("GPMPPI_COMPILE_AHEAD", "0")
    assert not compile_ahead.enabled()
    monkeypatch.setenv("GPMPPI_COMPILE_AHEAD", "1")
    assert compile_ahead.enabled() == (len(os.sched_getaffinity(0)) >= 2)


def test_a_child_with_other_critics_compiles_nothing_and_says_so_quietly() -> None:
    """A critic registered by the parent's own script (not importable by the child) would change the kernel's sums:
    the child must not cache a kernel without it, and the parent compiles the kernel itself, without a warning."""
    critics = [*compile_ahead._critic_names(), ("turning", "__main__", "turning_cost")]
    proc = subprocess.Popen([sys.executable, "-m", "gpmppi.mppi.compile_ahead"], stdin=subprocess.PIPE,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    proc.stdin.write(pickle.dumps((critics, ("not", "kernel", "arguments"))))
    proc.stdin.close()
    proc.stdin = None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert compile_ahead.CompileAhead(proc).wait() is False
    assert proc.returncode == compile_ahead._CRITICS_DIFFER


def test_a_failed_child_is_reported_and_the_plan_goes_on() -> None:
    proc = subprocess.Popen([sys.executable, "-c", "import sys; sys.stderr.write('no kernel here'); sys.exit(2)"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    with pytest.warns(RuntimeWarning, match=r"failed \(exit 2\); compiling it here instead: no kernel here"):
        assert compile_ahead.CompileAhead(proc).wait() is False


def test_a_child_given_bad_arguments_fails_without_caching_anything(tmp_path: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "gpmppi.mppi.compile_ahead"], stdin=subprocess.PIPE,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)})
    proc.stdin.write(pickle.dumps((compile_ahead._critic_names(), (np.zeros(3),))))
    proc.stdin.close()
    proc.stdin = None
    with pytest.warns(RuntimeWarning, match="compiling it here instead"):
        assert compile_ahead.CompileAhead(proc).wait() is False
    assert proc.returncode not in (0, compile_ahead._CRITICS_DIFFER)


def test_no_interpreter_to_start_means_compiling_here(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(compile_ahead, "enabled", lambda: True)
    monkeypatch.setattr(compile_ahead, "rollout_kernel_cached", lambda: False)
    monkeypatch.setattr(sys, "executable", str(tmp_path / "no-python"))
    with pytest.warns(RuntimeWarning, match="could not start a second process .* compiling it here"):
        assert compile_ahead.start(()) is None


def test_the_empty_task_the_child_compiles_for_has_every_task_bundles_types(monkeypatch: pytest.MonkeyPatch) -> None:
    """The child compiles the rollout kernel for `TaskBundle.for_types` (`Planner._start_compile_ahead`), not for the
    plan's task: a kernel of other types would be a compile wasted and the plan's own compiled after it. Lane, goal
    among circles (geodesic and straight) and goal with a costmap: each plan's task bundle, as the kernel gets it."""
    import numba

    from gpmppi.costmap import Costmap
    from gpmppi.mppi import backends
    from gpmppi.mppi.bundles import TaskBundle
    from gpmppi.scenarios import paper_obstacle_scene
    from gpmppi.tasks import GoalTask

    seen: list[tuple] = []
    rollouts = backends.rollouts

    def spy(backend: str, model: object, task: TaskBundle, *rest: object) -> object:
        seen.append(task.args())
        return rollouts(backend, model, task, *rest)

    monkeypatch.setattr(backends, "rollouts", spy)
    model = synthetic_model(nodes=4, n_train=20)
    goal = paper_obstacle_scene()
    grid = np.zeros((40, 40), dtype=np.int16)
    grid[20:24, 20:24] = 100
    with_grid = GoalTask(goal=goal.task.goal, tolerance=0.5, obstacles=goal.task.obstacles,
                         costmap=Costmap(grid, 0.1, (1.0, 1.0, 0.0)))
    for task, start, distance in ((circle_lane().task, circle_lane().start, "geodesic"),
                                  (goal.task, goal.start, "geodesic"), (goal.task, goal.start, "euclidean"),
                                  (with_grid, goal.start, "geodesic")):
        Planner(PlannerConfig(samples=32, horizon=8, goal_distance=distance), model).plan(start, task)
    want = numba.typeof(TaskBundle.for_types(8).args())
    assert len(seen) == 4 and all(numba.typeof(args) == want for args in seen)
