"""`python -m tools.plans_hex`: 45 seeded plans printed as hex, to compare two versions bit for bit (`diff`).

GP, EDD5 and unicycle planners x circle lane, square lane and the paper's obstacle scene, 5 plans each (S=1024, seed 7,
weights moving by a seeded walk): each plan's controls, cost and each critic's cost as hex, and a hash of the first
rollouts' costs and XY and the tightened bounds."""
import hashlib

import numpy as np

from gpmppi.gp.model_file import load_default_model
from gpmppi.models.kinematic_unicycle import kinematic_step
from gpmppi.mppi.planner import Planner, PlannerConfig
from gpmppi.scenarios import circle_lane, paper_obstacle_scene, square_lane


def main() -> None:
    model = load_default_model()
    rng = np.random.default_rng(3)
    n = 0
    for dyn in ("gp", "edd5", "unicycle"):
        for name, sc in (("circle", circle_lane()), ("square", square_lane()), ("goal", paper_obstacle_scene())):
            p = Planner(PlannerConfig(dynamics=dyn, backend="cpu", samples=1024, seed=7), model)
            x = sc.start.copy()
            w = np.array([0.5, 0.3, 0.2])
            for i in range(5):
                r = p.plan(x, sc.task, w)
                cc = ",".join(f"{k}={np.float64(v).tobytes().hex()}" for k, v in sorted(r.critic_costs.items()))
                rollouts = r.sample_costs.tobytes() + r.sample_states.tobytes() + r.tightened.tobytes()
                print(dyn, name, i, r.controls.tobytes().hex(), np.float64(r.cost).tobytes().hex(), cc,
                      hashlib.sha256(rollouts).hexdigest())
                n += 1
                x = kinematic_step(x, r.control, 0.1)
                w = np.clip(w + rng.normal(0, 0.02, 3), 0.01, 1.0)
                w /= w.sum()
    print("plans", n)


if __name__ == "__main__":
    main()
