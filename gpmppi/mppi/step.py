"""One sample's rollout step, written once: noise -> command -> model with its GP residual -> next state.

`sample_step` is the step of the CUDA kernel (one thread per sample, `cuda_backend`) and of the per-critic nominal
scorer (`cpu_serial.nominal_critic_costs`, which scores the nominal sequence as a sample with zero noise). Each adds
the step's stage cost its own way: the kernels the critics' sum (`costs.stage_cost`), the scorer each critic apart
(`costs.stage_critics`); the critics' registry builds both from the same terms.

The CPU kernel (`cpu_backend.rollout_worker`) runs the same two functions' parts, in phases over a group of samples
rather than one sample at a time: `rng.sampled_command` as a vector loop of the group's normals (`rng.normal_pair`)
then `rng.command_from_normals`; `dynamics.step_state` as the GP table rows of the whole group requested (prefetch),
then read, then `dynamics.advance`. A step one sample at a time would wait on each table read with nothing to
overlap it (docs/development.md, "The CPU rollout kernel").
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from gpmppi.mppi.dynamics import dyn_inputs, gp_inputs, step_state
from gpmppi.mppi.rng import sampled_command

__all__ = ["StepInputs", "sample_step", "step_inputs"]


class StepInputs(NamedTuple):
    """What a driver hands every sample's step, built once before its loops by `step_inputs`: the CPU kernel (its
    phases), the CUDA kernel and the per-critic nominal scorer all build it there, from the bundles."""

    limits: tuple  # `rng.sampled_command`'s (nominal, noise_std, u_lo, u_hi, (memory, innovation), (u_prev, rate_step))
    dyn: tuple  # `dynamics.step_state`'s (dyn_mode, coef, edd5) (`dynamics.dyn_inputs`)
    gp: tuple  # `dynamics.gp_residual`'s model fields (`dynamics.gp_inputs`)


@njit(cache=True, inline="always")
def step_inputs(model: tuple, sampling: tuple, noise_std: np.ndarray, memory: float, coef: np.ndarray) -> StepInputs:
    """The step's inputs from the model and sampling bundles' tuples, drawing with `noise_std` (the sampling bundle's;
    zeros to score the nominal) and AR(1) noise memory `memory` (its innovation sqrt(1 - memory^2)); `coef` the
    model's `dynamics.velocity_coefficients` (the caller's array: the CPU kernel allocates nothing, a CUDA thread
    fills its own)."""
    limits = (sampling.nominal, noise_std, sampling.u_lo, sampling.u_hi, (memory, math.sqrt(1.0 - memory * memory)),
              (sampling.u_prev, sampling.rate_step))
    return StepInputs(limits, dyn_inputs(model, coef), gp_inputs(model))


@njit(cache=True, inline="always")
def sample_step(
    seed: int, counter: int, k: int, inputs: StepInputs, scratch: tuple, dt: float, s: tuple, d: tuple,
) -> tuple[tuple, tuple, tuple, tuple]:
    """Step k of one sample: ((u0, u1) its command, (d0, d1) its unit noise, the next state (5 scalars), (var_v,
    var_w) the GP residual's variances of the step).

    `counter` is the noise counter of (iteration, sample, step) (`rng.noise_counter`); `inputs` the driver's
    `step_inputs`; `scratch` as `dynamics.step_state`; `s` the state before the step, `d` the unit noise of step
    k - 1."""
    nominal, noise_std, u_lo, u_hi, ar, first_step = inputs.limits
    u0, u1, d0, d1 = sampled_command(seed, counter, nominal, k, noise_std, u_lo, u_hi, ar, d[0], d[1], first_step)
    px, py, yaw, v, w, _mv, _mw, var_v, var_w = step_state(inputs.dyn, inputs.gp, scratch, dt, s, (u0, u1), 1.0)
    return (u0, u1), (d0, d1), (px, py, yaw, v, w), (var_v, var_w)
