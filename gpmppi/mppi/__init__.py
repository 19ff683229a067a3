"""MPPI: sampling, rollout + cost kernels (CPU numba, CUDA numba), weights, update, smoothing.

numba's OpenMP thread pool spin-waits between parallel regions by default; on a small machine
shared with other processes the spinning threads steal the cores the kernels need (measured: a
2-thread kernel ran 2x slower than 1 thread). Passive waiting is set here, before the pool starts,
unless the user chose a policy.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
