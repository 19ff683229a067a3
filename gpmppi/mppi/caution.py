"""The planner's caution on unknown ground (`TerrainWeights.unknown_active`, gpmppi/terrain/novelty.py).

While no trained ground explains the steps, the GP's residual mean and variance were never fitted to the ground under
the robot, and the chance constraints trust a variance that is too small. Three things change while it lasts, and
nothing else (the robot keeps driving the task):

- the residual variance the chance constraints propagate gets `unknown_residual_std`^2 more per step (v, omega):
  the lane is tightened and the obstacles inflated by more, so the plan keeps the margin the misfit eats. It is the
  size of the misfit measured on new grounds (docs/new_ground.md): the windowed mean residual of the best trained
  ground on sand and the grounds made for the tests;
- a lane's speed target is scaled by `unknown_speed_scale`: slower driving leaves each step's misfit less distance
  to act over;
- where the ground is unknown by its grip (the free-run channel: the robot slides), a goal task's commanded speed is
  bounded: `unknown_goal_speed` at the goal's tolerance, rising farther out as braking at `unknown_goal_decel`
  allows. On glare ice (grip 0.12 g) the robot came to the goal too fast to turn into it, circled it and slid into
  an obstacle; the bound lets it turn in, and costs time only near the goal. A ground that drags (sand, flagged by
  the one-step channel) still turns: there the goal keeps its speed.

Pure: a task and settings in, the task to plan for and the variance out. `PlannerCycle` applies them.
"""

from __future__ import annotations

from pydantic import BaseModel, Field

from gpmppi.tasks import Task


class CautionConfig(BaseModel):
    """What the planner changes while the ground is unknown (the planner service's settings inherit these)."""

    unknown_caution: bool = Field(True, description="be more careful while the terrain service says the ground is "
                                  "unknown (TerrainWeights.unknown_active): the settings below")
    unknown_speed_scale: float = Field(
        0.8, gt=0, le=1, description="lane tasks: the speed target is multiplied by this while the ground is "
        "unknown [1]")
    unknown_residual_std: tuple[float, float] = Field(
        (0.03, 0.03), description="extra one-step residual std (v [m/s], omega [rad/s]) the chance constraints "
        "propagate while the ground is unknown (added as variance to the GP's, every step of the horizon)")
    unknown_goal_speed: float | None = Field(
        0.6, gt=0, description="goal tasks, while the ground is unknown by its grip (the free-run channel): the "
        "commanded speed is at most this at the goal's tolerance [m/s], and farther out at most what braking at "
        "`unknown_goal_decel` comes down to it from (None: no bound)")
    unknown_goal_decel: float = Field(
        0.5, ge=0, description="goal tasks, while the ground is unknown by its grip: the braking [m/s^2] the speed "
        "bound rises by with the distance to the goal (0: the bound is `unknown_goal_speed` everywhere)")


def cautious_task(task: Task, config: CautionConfig, grip: bool = False) -> Task:
    """The task to plan for while the ground is unknown, as its kind says (`cautious`): a lane at the scaled speed
    target; a goal approached at the bounded speed where the ground is unknown by its grip (`grip`: the free-run
    channel said so), else unchanged (its care is then the obstacles inflated by the extra variance)."""
    goal = config.unknown_goal_speed
    approach = None if goal is None or not grip else (goal, config.unknown_goal_decel)
    return task.cautious(config.unknown_speed_scale, approach)


def extra_variance(config: CautionConfig) -> tuple[float, float]:
    """The per-step residual variance [(m/s)^2, (rad/s)^2] added while the ground is unknown."""
    sv, sw = config.unknown_residual_std
    return float(sv) ** 2, float(sw) ** 2
