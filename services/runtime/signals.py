"""Stop signals (SIGINT, SIGTERM) handled without taking a lock in the signal handler.

Python runs a signal handler on the main thread between two bytecodes, possibly while that thread holds a lock: the
lock of the `threading.Event` it is waiting on, say, in the middle of `Event.wait`. A handler that calls `Event.set`
then waits for a lock its own thread holds, and the process hangs on Ctrl-C, the worst way for a robot's service (or
its recorder) to stop. So the handler here only writes the signal's number to a pipe (no lock), and a small thread
reading that pipe calls the callback, where taking a lock only waits for the main thread to let go of it.

The pipe is also the process's signal wakeup fd (`signal.set_wakeup_fd`): the interpreter's C-level handler writes
the signal's number to it on whichever thread the kernel delivered the signal to. A process-directed signal may land
on another thread than the main one (a thread that changes its signal mask, as glibc's `pthread_create` does, picks
up a signal still pending for the process): the main thread, blocked in `Event.wait`, is then never interrupted, and
a Python-level handler would run only when it next runs Python code, never for a router that waits on its stop Event
alone. A router hung so on SIGINT once under load (its signal thread waiting on the pipe, its main thread in
`Event.wait`); SIGINT sent to its signal thread alone (`tgkill`) hangs it every time without the wakeup fd
(`tests/test_stop_signals.py`).
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable, Iterable
from types import FrameType
from typing import Any

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopSignals:
    """Calls `on_signal(signum)` from its own thread for each stop signal received, until `restore()`.

    Install it from the main thread (as `signal.signal` requires); `restore()` puts the previous handlers back and
    ends the thread. A context manager does both."""

    def __init__(self, on_signal: Callable[[int], Any], signums: Iterable[int] = STOP_SIGNALS) -> None:
        self._on_signal = on_signal
        self._signums = frozenset(signums)
        self._read_fd, self._write_fd = os.pipe()
        os.set_blocking(self._write_fd, False)  # a full pipe drops a repeat signal, never blocks the handler
        self._thread = threading.Thread(target=self._deliver, name="stop-signals", daemon=True)
        self._thread.start()
        self._previous = {s: signal.signal(s, self._handler) for s in self._signums}
        # the C-level handler writes each signal's number here, on the thread that received it (module docstring)
        self._previous_wakeup_fd = signal.set_wakeup_fd(self._write_fd, warn_on_full_buffer=False)

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        """The Python-level handler (on the main thread, whenever it next runs Python code): nothing to do, the
        wakeup fd has delivered the signal already; installed so that the signal is Python's to handle."""

    def _deliver(self) -> None:
        try:
            while data := os.read(self._read_fd, 64):  # b"" once restore() closed the write end
                for signum in data:
                    if signum in self._signums:  # the wakeup fd carries every Python-handled signal (SIGALRM, ...)
                        self._on_signal(signum)
        finally:
            os.close(self._read_fd)

    def restore(self) -> None:
        for s, previous in self._previous.items():
            signal.signal(s, previous)
        self._previous = {}
        if self._write_fd >= 0:
            current = signal.set_wakeup_fd(self._previous_wakeup_fd)
            if current != self._write_fd:  # set by another since: that one stays
                signal.set_wakeup_fd(current)
            os.close(self._write_fd)
            self._write_fd = -1

    def __enter__(self) -> StopSignals:
        return self

    def __exit__(self, *exc: object) -> None:
        self.restore()
