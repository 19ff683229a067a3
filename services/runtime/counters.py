"""What a service counts for its heartbeat (`Counters`): messages received, rejected, published, cycles, the last
error, and its own named counts, conditions and status."""

from __future__ import annotations

import threading
from typing import Literal


class Counters:
    def __init__(self) -> None:
        self.received = 0
        self.rejected = 0
        self.published = 0
        self.cycles = 0
        self.last_error = ""
        # service-specific health, sent in each heartbeat: named counters, named conditions, overall status
        self.counts: dict[str, int] = {}
        self.flags: dict[str, bool] = {}
        self.status: Literal["ok", "degraded", "failing"] = "ok"
        self.lock = threading.Lock()

    def count(self, name: str, n: int = 1) -> None:
        """Add n to the named counter `name` (reported in the heartbeat's `counts`)."""
        with self.lock:
            self.counts[name] = self.counts.get(name, 0) + n
