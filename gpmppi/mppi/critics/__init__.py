"""The planner's critics, after Nav2's critic plug-ins: one module per critic (`base.Critic`), registered here.

A new critic is a module like `speed.py` (its `CRITIC`: name, default weight and parameters, task kinds, stage or
terminal, term; a stateful critic also its `base.StepState`, like `lane_exit.py`) and one `register` line below.
Everything else derives from the registry (`registry.layout`): the cost bundle, the config section `critics:`, the
kernels' summed cost and the per-critic split, the state the drivers carry, on CPU and CUDA.
"""

from __future__ import annotations

from gpmppi.mppi.critics import collision, costmap, deviation, goal, lane_exit, slip, speed, terminal, variance
from gpmppi.mppi.critics.registry import register

register(variance.CRITIC)
register(deviation.CRITIC)
register(slip.CRITIC)
register(lane_exit.CRITIC)
register(speed.CRITIC)
register(collision.CRITIC)
register(costmap.CRITIC)
register(goal.CRITIC)
register(terminal.CRITIC)
