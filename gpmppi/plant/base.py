"""The interface every simulated robot implements (the sim service drives any of them)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Plant(Protocol):
    """A simulated robot: state `[X, Y, yaw, v, omega]`, command `[v_ref, omega_ref]`."""

    dt: float  # the plant's internal step [s]

    def reset(self, state: np.ndarray) -> None:
        """Place the robot at `state`."""
        ...

    def step(self, command: np.ndarray, duration: float) -> np.ndarray:
        """Apply `command` for `duration` seconds; return the true state."""
        ...

    def measure(self) -> np.ndarray:
        """The current state with sensor noise (seeded)."""
        ...

    def set_terrain(self, name: str) -> None:
        """Switch the terrain under the robot."""
        ...
