"""One sample's rollout step, written once: noise -> command -> model with its GP residual -> next state.

`sample_step` is the step of the CUDA kernel (one thread per sample, `cuda_backend`) and of the per-critic nominal
scorer (`cpu_backend.nominal_critic_costs`, which scores the nominal sequence as a sample with zero noise). Each adds
the step's stage cost its own way: the kernels the critics' sum (`costs.stage_cost`), the scorer each critic apart
(`costs.stage_critics`); the critics' registry builds both from the same terms.

The CPU kernel (`cpu_backend.rollout_worker`) runs the same two functions' parts, in phases over a group of samples
rather than one sample at a time: `rng.sampled_command` as a vector loop of the group's normals (`rng.normal_pair`)
then `rng.command_from_normals`; `dynamics.step_state` as the GP table rows of the whole group requested (prefetch),
then read, then `dynamics.advance`. A step one sample at a time would wait on each table read with nothing to
overlap it (docs/development.md, "The CPU rollout kernel").
"""

from __future__ import annotations

from numba import njit

from gpmppi.mppi.dynamics import step_state
from gpmppi.mppi.rng import sampled_command

__all__ = ["sample_step"]


@njit(cache=True, inline="always")
def sample_step(
    seed: int, counter: int, k: int, limits: tuple, dyn: tuple, gp: tuple, scratch: tuple, dt: float, s: tuple,
    d: tuple,
) -> tuple[tuple, tuple, tuple, tuple]:
    """Step k of one sample: ((u0, u1) its command, (d0, d1) its unit noise, the next state (5 scalars), (var_v,
    var_w) the GP residual's variances of the step).

    `counter` is the noise counter of (iteration, sample, step) (`rng.noise_counter`); `limits` = (nominal,
    noise_std, u_lo, u_hi, (noise memory, innovation), (command in effect, rate step)) as `rng.sampled_command`
    takes them; `dyn`, `gp`, `scratch` as `dynamics.step_state`; `s` the state before the step, `d` the unit noise
    of step k - 1."""
    nominal, noise_std, u_lo, u_hi, ar, first_step = limits
    u0, u1, d0, d1 = sampled_command(seed, counter, nominal, k, noise_std, u_lo, u_hi, ar, d[0], d[1], first_step)
    px, py, yaw, v, w, _mv, _mw, var_v, var_w = step_state(dyn, gp, scratch, dt, s, (u0, u1), 1.0)
    return (u0, u1), (d0, d1), (px, py, yaw, v, w), (var_v, var_w)
