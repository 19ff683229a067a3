"""torch on one intra-op thread for the tests' own GPyTorch fits and references.

On the small batched matrices of these GPs a second thread only waits, and in the suite it waits for a core the
other workers hold: alone with another job on the second core, the plain likelihood fit of tests/test_gp_fit.py
took 0.54-0.64 CPU s on one thread against 4.1-7.6 on two, the GPyTorch reference of tests/test_gp_grid_accuracy.py
0.36 against 1.3-1.6 (docs/development.md). `gpmppi.gp.fit.fit_hyperparameters` fits on one thread for the same
reason."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator


@contextlib.contextmanager
def one_torch_thread() -> Iterator[None]:
    """torch's intra-op threads at 1 inside the block, as they were after it."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
