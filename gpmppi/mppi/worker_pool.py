"""The threads that run the CPU rollout kernel beside the planning thread (`cpu_backend.rollout_kernel`)."""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Callable

__all__ = ["WorkerPool"]


class WorkerPool:
    """Threads kept between plans, each running a nogil kernel on request; the calling thread runs it too.

    Started lazily, and anew in a forked child (a fork keeps the parent's threads' objects, not the threads)."""

    def __init__(self) -> None:
        self._pid = -1
        self._inboxes: list[queue.SimpleQueue] = []
        self._done: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()

    def _loop(self, inbox: queue.SimpleQueue) -> None:
        while True:
            fn, args = inbox.get()
            try:
                fn(*args)
                self._done.put(None)
            except BaseException as exc:  # handed to the caller, which raises it
                self._done.put(exc)

    def run(self, fn: Callable, calls: list[tuple]) -> None:
        """`fn(*calls[0])` on this thread, `fn(*calls[i])` on pool thread i; raises what any of them raised."""
        helpers = len(calls) - 1
        with self._lock:  # one kernel at a time through the pool (its callers may be several threads)
            if self._pid != os.getpid():
                self._pid, self._inboxes, self._done = os.getpid(), [], queue.SimpleQueue()
            while len(self._inboxes) < helpers:
                inbox: queue.SimpleQueue = queue.SimpleQueue()
                threading.Thread(target=self._loop, args=(inbox,), daemon=True, name="gpmppi-rollout").start()
                self._inboxes.append(inbox)
            for inbox, args in zip(self._inboxes[:helpers], calls[1:], strict=True):
                inbox.put((fn, args))
            error: BaseException | None = None
            try:
                fn(*calls[0])
            except BaseException as exc:
                error = exc
            for _ in range(helpers):
                result = self._done.get()
                error = error or result
            if error is not None:
                raise error
