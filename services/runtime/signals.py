"""Stop signals (SIGINT, SIGTERM) handled without taking a lock in the signal handler.

Python runs a signal handler on the main thread between two bytecodes, possibly while that thread holds a lock: the
lock of the `threading.Event` it is waiting on, say, in the middle of `Event.wait`. A handler that calls `Event.set`
then waits for a lock its own thread holds, and the process hangs on Ctrl-C, the worst way for a robot's service (or
its recorder) to stop. So the handler here only writes the signal's number to a pipe (no lock), and a small thread
reading that pipe calls the callback, where taking a lock only waits for the main thread to let go of it.
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
        self._read_fd, self._write_fd = os.pipe()
        os.set_blocking(self._write_fd, False)  # a full pipe drops a repeat signal, never blocks the handler
        self._thread = threading.Thread(target=self._deliver, name="stop-signals", daemon=True)
        self._thread.start()
        self._previous = {s: signal.signal(s, self._handler) for s in signums}

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        try:
            os.write(self._write_fd, bytes([signum]))
        except OSError:  # the pipe is full (signals are being delivered) or closed (restored meanwhile)
            pass

    def _deliver(self) -> None:
        try:
            while data := os.read(self._read_fd, 64):  # b"" once restore() closed the write end
                for signum in data:
                    self._on_signal(signum)
        finally:
            os.close(self._read_fd)

    def restore(self) -> None:
        for s, previous in self._previous.items():
            signal.signal(s, previous)
        self._previous = {}
        if self._write_fd >= 0:
            os.close(self._write_fd)
            self._write_fd = -1

    def __enter__(self) -> StopSignals:
        return self

    def __exit__(self, *exc: object) -> None:
        self.restore()
