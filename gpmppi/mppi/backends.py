"""Backend selection and the one call the planner makes per iteration: `rollouts`.

Both backends take the same bundles (`gpmppi.mppi.bundles`) and draw the same noise, so they agree to rounding.
"""

from __future__ import annotations

import numpy as np

from gpmppi.mppi.bundles import CRITICS, CostBundle, ModelBundle, Outputs, SamplingBundle, TaskBundle
from gpmppi.mppi.cpu_backend import rollout_kernel
from gpmppi.mppi.cpu_serial import nominal_critic_costs, softmax_update

__all__ = ["critic_costs", "device_inputs", "resolve", "rollouts", "softmax_update"]


def cuda_available() -> bool:
    try:
        from numba import cuda

        return bool(cuda.is_available())
    except Exception:  # a broken driver install means: no CUDA
        return False


def resolve(backend: str) -> str:
    """'auto' -> 'cuda' when numba sees a GPU (or the simulator), else 'cpu'; 'cuda' without one is an error."""
    if backend == "cpu":
        return "cpu"
    if backend == "cuda":
        if not cuda_available():
            raise ValueError("backend='cuda' but numba.cuda finds no GPU; use backend='cpu' or 'auto'")
        return "cuda"
    if backend == "auto":
        return "cuda" if cuda_available() else "cpu"
    raise ValueError(f"backend must be 'auto', 'cpu' or 'cuda', got {backend!r}")


def rollouts(
    backend: str, model: ModelBundle, task: TaskBundle, sampling: SamplingBundle, cost: CostBundle, samples: int,
    n_xy: int, device: object | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Perturbations (S, N, 2) float32, costs (S,), XY of the first n_xy rollouts (n_xy, N+1, 2).

    `device`: CUDA only, the caller's `cuda_backend.DeviceInputs` (its inputs kept on the device between calls)."""
    out = Outputs.allocate(samples, sampling.nominal.shape[0], n_xy)
    args = (model.args(), task.args(), sampling.args(), cost.args(), out.args())
    if backend == "cuda":
        from gpmppi.mppi.cuda_backend import cuda_rollouts

        cuda_rollouts(*args, device=device)  # type: ignore[arg-type]
    else:
        rollout_kernel(*args)
    return out.eps_out, out.cost_out, out.xy_out


def device_inputs(backend: str) -> object | None:
    """What keeps a planner's kernel inputs on its device between plans (`cuda_backend.DeviceInputs`); None on the
    CPU."""
    if backend != "cuda":
        return None
    from gpmppi.mppi.cuda_backend import DeviceInputs

    return DeviceInputs()


def critic_costs(model: ModelBundle, task: TaskBundle, sampling: SamplingBundle, cost: CostBundle) -> dict[str, float]:
    """Each critic's cost of the sampling bundle's nominal sequence, by name (serial, on the CPU)."""
    values = nominal_critic_costs(model.args(), task.args(), sampling.args(), cost.args())
    return {name: float(v) for name, v in zip(CRITICS, values, strict=True)}


def effective_sample_size(weights: np.ndarray) -> float:
    """Kish's effective sample size 1 / sum(w^2) of normalised weights (sum 1), as `softmax_update` returns them;
    0 for all-zero weights (every cost infinite)."""
    w = np.asarray(weights, dtype=np.float64)
    sq = float(np.dot(w, w))
    return 1.0 / sq if sq > 0.0 else 0.0
