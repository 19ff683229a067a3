"""How a service shares the machine: subscription inboxes that wake the service loop on arrival (no polling
delay on the control path), and the process's CPU priority and numba thread count."""

from __future__ import annotations

import os
import queue
import sys
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import zenoh

if TYPE_CHECKING:
    from services.runtime.node_settings import NodeSettings


class Inbox:
    """Samples a Zenoh callback delivered, waiting for the service loop; every arrival calls `wake` (the node's
    loop waits on an event, not a fixed sleep, so input is handled at once).

    Newest-only keeps one sample (a newer one replaces it) and hands each sample it replaced unread to
    `on_displaced`, on the callback's thread, after waking the loop: the control loop takes only the newest, but
    a bad message replaced before the loop took it is still seen (`TypedSubscription` counts and logs it). FIFO
    keeps up to `capacity` and then makes the sender wait, as Zenoh's FifoChannel does: nothing is dropped while
    the node runs."""

    def __init__(self, wake: Callable[[], None], closing: Callable[[], bool], newest_only: bool, capacity: int,
                 on_displaced: Callable[[zenoh.Sample], object] | None = None) -> None:
        self._wake = wake
        self._closing = closing
        self._newest_only = newest_only
        self._waiting: zenoh.Sample | None = None  # newest-only: the sample not taken yet
        self._swap = threading.Lock()  # newest-only: replacing the waiting sample and taking it are one step each
        self._on_displaced = on_displaced
        self._fifo: queue.Queue[zenoh.Sample] | None = None if newest_only else queue.Queue(maxsize=capacity)

    def push(self, sample: zenoh.Sample) -> None:
        """Called on Zenoh's callback thread."""
        if self._newest_only:
            with self._swap:
                displaced, self._waiting = self._waiting, sample
            self._wake()
            if displaced is not None and self._on_displaced is not None:
                self._on_displaced(displaced)
            return
        assert self._fifo is not None
        while True:
            try:
                self._fifo.put(sample, timeout=0.1)
                break
            except queue.Full:
                if self._closing():  # nobody will drain it any more
                    return
        self._wake()

    def take(self) -> zenoh.Sample | None:
        """The oldest waiting sample (newest-only: the one waiting), or None."""
        if self._newest_only:
            with self._swap:
                sample, self._waiting = self._waiting, None
            return sample
        assert self._fifo is not None
        try:
            return self._fifo.get_nowait()
        except queue.Empty:
            return None


def apply_process_settings(settings: NodeSettings) -> None:
    """CPU priority (`nice`, only ever lowered) and numba's thread count, before the service starts its work."""
    if settings.nice:
        os.nice(settings.nice)
    if settings.numba_threads is not None:
        n = settings.numba_threads
        n = n if n > 0 else max(1, (os.cpu_count() or 1) + n)
        if "numba" in sys.modules:
            import numba

            numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))  # this thread's kernels (the loop's)
        else:  # read when numba is imported
            os.environ["NUMBA_NUM_THREADS"] = str(n)


def process_age_s() -> float | None:
    """Seconds since this process was created (Linux: /proc/self/stat, 10 ms steps), or None elsewhere: start-up
    logs count from the process's creation, so interpreter start and imports are in the figure."""
    try:
        with open("/proc/self/stat") as f:
            # field 22 (starttime, clock ticks after boot); the command name (field 2) may hold spaces: split after it
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        return time.clock_gettime(time.CLOCK_BOOTTIME) - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        return None
