"""MPPI: sampling, rollout + cost kernels (CPU numba, CUDA numba), weights, update, smoothing."""
