"""A costmap plan's rollouts and costs with only the costmap critic weighed, on a backend (tests/test_costmap.py runs it
in-process on the CPU and in a child under the CUDA simulator): `python tests/costmap_case.py cuda` prints it as JSON.
"""

from __future__ import annotations

import json
import sys

import numpy as np
from cached_models import synthetic_model

from gpmppi.costmap import Costmap
from gpmppi.mppi import backends
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.tasks import GoalTask

ONLY_COSTMAP = {name: {"enabled": False} for name in ("variance", "collision", "goal", "terminal")}


def case_grid(seed: int = 3) -> Costmap:
    """An 80 x 80 grid at 5 cm, rotated 0.3 rad: a lethal block 1 m ahead of the start (`START`), a wall beside it,
    graded and unknown cells at random (seeded)."""
    rng = np.random.default_rng(seed)
    values = np.zeros((80, 80), dtype=np.int16)
    graded = rng.random(values.shape) < 0.3
    values[graded] = rng.integers(1, 99, int(np.count_nonzero(graded)))
    values[rng.random(values.shape) < 0.02] = -1
    values[30:45, 40:55] = 100
    values[10:12, 10:70] = 100
    return Costmap(values, 0.05, (-0.5, -1.0, 0.3))


def start_state() -> np.ndarray:
    """At grid cell (row 37, column 20), heading along the grid's x axis towards the block."""
    c, s = np.cos(0.3), np.sin(0.3)
    gx, gy = 20.5 * 0.05, 37.5 * 0.05
    return np.array([-0.5 + c * gx - s * gy, -1.0 + s * gx + c * gy, 0.3, 0.8, 0.0])


def run(backend: str, samples: int = 64, horizon: int = 8) -> dict:
    grid = case_grid()
    task = GoalTask(goal=np.array([4.0, 4.0]), obstacles=np.array([[5.0, -3.0, 0.2]]), costmap=grid)
    cfg = PlannerConfig(backend=backend, samples=samples, horizon=horizon, robot_radius=0.1, noise_std=[1.5, 2.5],
                        critics={**ONLY_COSTMAP, "costmap": {"weight": 50.0, "value_scale": 0.2}})
    planner = Planner(cfg, synthetic_model(nodes=4, n_train=20))
    x = start_state()
    kind = planner.kind(task)
    model = planner.terrain.set_weights(np.array([0.5, 0.3, 0.2]))
    # covariances that grow along the horizon, with some correlation: the grid's radius grows with them
    covs = np.zeros((horizon + 1, 5, 5))
    for k in range(horizon + 1):
        covs[k, :2, :2] = np.array([[0.004, 0.001], [0.001, 0.002]]) * k
    states = np.repeat(x[None, :], horizon + 1, axis=0)
    bounds, _ = kind.bounds(task, states, covs)
    bundle = kind.task_bundle(task, bounds, x)
    sampling = planner._sampling(x, np.tile([0.8, 0.0], (horizon, 1)), kind.noise_std)
    _eps, costs, xy = backends.rollouts(planner.backend, model, bundle, sampling, kind.cost, samples, samples,
                                        planner.device)
    return {"costs": costs.tolist(), "xy": xy.tolist(), "radii": bounds[:, -1].tolist(), "covs": covs.tolist(),
            "weight": 50.0, "value_scale": 0.2, "robot_radius": 0.1}


if __name__ == "__main__":
    print("RESULT", json.dumps(run(sys.argv[1])))
