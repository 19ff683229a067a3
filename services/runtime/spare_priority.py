"""A warm spare starts at a lower CPU priority and takes the service's own at its go.

A spare (services.launch.spares) does its whole start before its go: the imports, the model file, the compiled
kernels and a warm-up plan, seconds of CPU. The launcher makes the spares right after their services are up, which
is when the robot starts to drive; at the same priority a spare's start competes with the control path it backs
(docs/faults.md, "A spare's start yields the CPU"). The launcher sets `GPMPPI_SPARE_NICE` in a spare's
environment: the process raises its niceness by that much before its imports (`lower_for_standby`) and takes it back
at its go, in every thread it made meanwhile (`restore_at_go`), so the service runs at its own priority once it
takes over.

Linux keeps a niceness per thread, and lowering it again (a smaller value) takes `CAP_SYS_NICE` or an
`RLIMIT_NICE` that allows it (systemd's `LimitNICE=`, `ulimit -e`): without either the spare keeps running at the
lower priority after it took over, and says so in its log (docs/faults.md).

Only the standard library: `services.run` calls `lower_for_standby` before a service's imports.
"""

from __future__ import annotations

import os

SPARE_NICE_ENV = "GPMPPI_SPARE_NICE"
_TASKS = "/proc/self/task"

_raised_by = 0  # how much this process raised its niceness while it stands by (0: not a spare, or restored)


def lower_for_standby() -> int:
    """Raise this thread's niceness by `GPMPPI_SPARE_NICE` (a launcher's warm spare; nothing without it): the
    threads made from here on inherit it. Returns the amount."""
    global _raised_by
    text = os.environ.pop(SPARE_NICE_ENV, "")  # not for this process's own children
    if not text.isdigit() or int(text) == 0:
        return 0
    before = os.getpriority(os.PRIO_PROCESS, 0)
    after = os.nice(int(text))
    _raised_by = after - before  # the kernel caps niceness at 19
    return _raised_by


def thread_ids() -> list[int]:
    """This process's threads (Linux: /proc/self/task); just this one elsewhere."""
    try:
        return [int(t) for t in os.listdir(_TASKS)]
    except OSError:
        return [0]


def restore_at_go() -> str | None:
    """Take back what `lower_for_standby` added, in every thread of the process (twice: a thread made while the
    first pass ran is met by the second). None when done or nothing to do; else one line saying why not (no
    permission to lower a niceness again), for the log."""
    global _raised_by
    if _raised_by == 0:
        return None
    amount, _raised_by = _raised_by, 0
    done: set[int] = set()
    for _ in range(2):
        for tid in thread_ids():
            if tid in done:
                continue
            try:
                os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) - amount)
            except ProcessLookupError:  # the thread ended meanwhile
                pass
            except PermissionError:
                return (f"this spare keeps the {amount} of niceness it started with: lowering it again needs "
                        "CAP_SYS_NICE or an RLIMIT_NICE that allows it (systemd LimitNICE=, ulimit -e)")
            done.add(tid)
    return None
