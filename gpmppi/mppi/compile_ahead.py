"""On a cold kernel cache, the rollout kernel compiled in a second process while this one compiles the rest.

numba compiles under one lock per process, so a cold compile of one planner configuration runs on one core: ~35 s
on a 2-core machine, of which the rollout kernel is ~14 s (~20 s with the GP residual it calls) and the serial
kernels around it (`propagate`, the per-critic scorer, the lane lookup) the rest. Neither needs the other compiled.
So a planner's first plan on a cold cache hands the rollout kernel's arguments to a child process
(`python -m gpmppi.mppi.compile_ahead`), which calls the kernel once (compiling it into the shared numba cache) and
exits; meanwhile this process compiles the serial kernels, and then loads the rollout kernel from the cache.

The child starts at once: its task is an empty one of the same types (`TaskBundle.for_types`), so it does not wait
for the plan's bounds and lane lookup, which this process compiles after its model step (`propagate`, whose GP
residual the child then loads). It first compiles the per-critic scorer's split critics (`_compile_critic_split`),
which this process meets last, then the kernel: the two processes' shares of the compile are then about even.

The results do not depend on it: a kernel loaded from the cache runs the machine code it was compiled to, and
every function it shares with the serial kernels is either inlined in numba's IR or linked as object code in both
histories; `tests/test_determinism.py` compiles one history this way and one in a single process, and compares the
bytes of their plans. `GPMPPI_COMPILE_AHEAD=0` turns it off (one process compiles everything, in order).
"""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np

from gpmppi.mppi.bundles import CRITICS
from gpmppi.mppi.costs import stage_critics, start_state, terminal_critics, weight_vector
from gpmppi.mppi.cpu_backend import rollout_kernel, rollout_worker
from gpmppi.mppi.critics.registry import layout

__all__ = ["CompileAhead", "enabled", "rollout_kernel_cached", "start"]

# the longest a plan waits for the child: past it (a stuck or starved child) this process compiles the kernel itself
WAIT_S = 600.0
_CRITICS_DIFFER = 3  # the child's exit status when its registered critics are not this process's


def enabled() -> bool:
    """Whether compiling ahead is allowed here: not turned off, and a second core to run it on."""
    if os.environ.get("GPMPPI_COMPILE_AHEAD", "1") == "0":
        return False
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return cores >= 2


def rollout_kernel_cached() -> bool:
    """Whether the CPU rollout kernel is compiled in this process or in numba's cache for this machine (any
    signature: every planner configuration calls it with the same types). True when that cannot be told."""
    if rollout_worker.signatures:
        return True
    try:
        index = rollout_worker._cache._cache_file._load_index()  # empty when the sources changed since
        magic = rollout_worker.targetctx.codegen().magic_tuple()
    except Exception:  # numba's private cache layout changed: do not start a second process on a guess
        return True
    return any(key[1] == magic for key in index)


def _critic_names() -> list[tuple[str, str, str]]:
    """The registered critics as (name, term module, term name): the child must compile the same sums."""
    return [(c.name, c.term.py_func.__module__, c.term.py_func.__qualname__) for c in layout().critics]


class CompileAhead:
    """A child process compiling the rollout kernel into the numba cache (`start`)."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self._proc = proc

    def wait(self) -> bool:
        """Wait for the child; True when it compiled the kernel (else this process compiles it when it calls it)."""
        try:
            _, err = self._proc.communicate(timeout=WAIT_S)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.communicate()
            warnings.warn(f"the rollout kernel's compile in a second process took over {WAIT_S:.0f} s; compiling "
                          "it here instead", RuntimeWarning, stacklevel=2)
            return False
        if self._proc.returncode == 0:
            return True
        if self._proc.returncode != _CRITICS_DIFFER:
            tail = err.decode(errors="replace")[-2000:] if err else ""
            warnings.warn(f"the rollout kernel's compile in a second process failed (exit {self._proc.returncode}); "
                          f"compiling it here instead: {tail}", RuntimeWarning, stacklevel=2)
        return False


def start(kernel_args: tuple) -> CompileAhead | None:
    """Start compiling the CPU rollout kernel for `kernel_args` (`rollout_kernel`'s five bundle tuples) in a child
    process, when it is not cached and compiling ahead is enabled; None otherwise."""
    if not enabled() or rollout_kernel_cached():
        return None
    from gpmppi.mppi.kernel_cache import cache_folder

    payload = pickle.dumps((_critic_names(), kernel_args), protocol=pickle.HIGHEST_PROTOCOL)
    root = str(Path(__file__).resolve().parents[2])  # the folder that holds this gpmppi package
    path = os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])])
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_folder()), PYTHONPATH=path)
    try:
        proc = subprocess.Popen([sys.executable, "-m", "gpmppi.mppi.compile_ahead"], stdin=subprocess.PIPE,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    except OSError as e:  # no interpreter to start (an embedded Python): compile here, as without it
        warnings.warn(f"could not start a second process to compile the rollout kernel ({e}); compiling it here",
                      RuntimeWarning, stacklevel=2)
        return None
    assert proc.stdin is not None
    try:
        proc.stdin.write(payload)
        proc.stdin.close()
    except OSError:  # the child ended at once: its exit status and message say why (`CompileAhead.wait`)
        pass
    proc.stdin = None  # written and closed: `communicate` must not touch it again
    return CompileAhead(proc)


def _exit_with_parent() -> None:
    """Have Linux stop this process when its parent exits (a planner stopped mid-compile leaves nothing behind)."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: the child ends when its compile does
        pass


def _main() -> int:
    _exit_with_parent()
    if os.getppid() == 1:  # the parent already gone
        return 1
    critics, kernel_args = pickle.loads(sys.stdin.buffer.read())
    if _critic_names() != critics:  # e.g. a critic registered by the parent's own script: its sums differ
        return _CRITICS_DIFFER
    _compile_critic_split(*kernel_args[:4])
    rollout_kernel(*kernel_args)
    return 0


def _compile_critic_split(model: tuple, task: tuple, sampling: tuple, cost: tuple) -> None:
    """Compile the per-critic scorer's split critics (`costs.stage_critics`, `costs.terminal_critics`) into the cache,
    called as `cpu_serial.nominal_critic_costs` calls them (the same types): the parent compiles its model step
    first (`propagate`) and meets them ~10 s later, by when they are cached here, and this process has the time (the
    parent's share of a cold compile was the larger)."""
    cost_w = weight_vector(cost)
    state = start_state(cost_w)
    x0 = sampling.x0
    s = (float(x0[0]), float(x0[1]), float(x0[2]), float(x0[3]), float(x0[4]))
    out = np.zeros(len(CRITICS))
    stage_critics(cost_w, task, task.tightened_hw[1], task.radii[1], state, s, (0.0, 0.0), (0.0, 0.0), out)
    terminal_critics(cost_w, task, task.tightened_hw[-1], task.radii[-1], state, s, out)


if __name__ == "__main__":
    sys.exit(_main())
