"""The planner's model swap: a `ModelUpdate` (a ground was learned) -> the new profile loaded, checked against its
sha256 and its planner built on a thread, then handed to `PlannerCycle.swap_planner` between two plans.

Loading (0.2-0.6 s: zlib and numpy release the GIL) and building the planner (its tables) happen off the loop, so no
state waits for them; the swap itself only exchanges references. A file whose bytes are not the announced ones is
refused in one line, and the planner plans on with the model it has.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from schemas import ModelUpdate

if TYPE_CHECKING:
    from gpmppi.gp.model_file import GPModel
    from gpmppi.mppi.config import PlannerConfig
    from gpmppi.mppi.cycle import PlannerCycle
    from gpmppi.mppi.planner import Planner
    from services.runtime.node import Node


@dataclass
class Swap:
    """A loaded profile and its planner, ready to take over (or the reason there is none)."""

    update: ModelUpdate
    model: GPModel | None = None
    planner: Planner | None = None
    error: str = ""


class ModelSwap:
    """Builds the planner of each new model version off the loop; `take()` hands it over when it is ready."""

    def __init__(self, config: PlannerConfig, sha256: str | None = None, version: int = 0,
                 search_dir: str | None = None) -> None:
        self.config = config
        self.search_dir = search_dir  # also holds announced profiles as <sha256>.npz (a replay's, from its log)
        self.sha256 = sha256  # the profile planned with (None: not known, e.g. the shipped one)
        self.version = version  # the `ModelUpdate.version` planned with (0: the profile the planner started with)
        self._pool: ThreadPoolExecutor | None = None
        self._future: Future[Swap] | None = None
        self._wanted: str | None = None  # the sha256 being loaded
        self._grounds: tuple[str, ...] = ()  # and its grounds

    def offer(self, update: ModelUpdate) -> str | None:
        """Start loading `update`'s profile unless it is the one planned with or being loaded; the log line."""
        if update.sha256 in (self.sha256, self._wanted):
            return None
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="model-swap")
        if self._future is not None:  # a newer version supersedes the one loading: it is dropped when done
            self._future.cancel()
        self._wanted, self._grounds = update.sha256, tuple(update.grounds)
        self._future = self._pool.submit(self._build, update)
        return f"model version {update.version} ({', '.join(update.grounds)}): loading {update.path}"

    def _build(self, update: ModelUpdate) -> Swap:
        from gpmppi.gp.model_file import ModelFileError
        from gpmppi.gp.profile_store import load_checked
        from gpmppi.mppi.planner import Planner

        path = update.path
        if self.search_dir is not None and (found := Path(self.search_dir) / f"{update.sha256}.npz").is_file():
            path = str(found)  # the recording's copy of what was announced (the original may be gone or replaced)
        try:
            model = load_checked(path, update.sha256)
            if list(model.terrains) != list(update.grounds):
                raise ModelFileError(f"{update.path}: grounds {model.terrains} are not the announced {update.grounds}")
            return Swap(update, model, Planner(self.config, model))
        except (ModelFileError, ValueError, OSError) as e:
            return Swap(update, error=f"model version {update.version} not taken: {e}")

    @property
    def loading(self) -> tuple[str, ...] | None:
        """The grounds of the model being loaded (None: none is)."""
        return None if self._future is None else self._grounds

    def take(self) -> Swap | None:
        """The swap once its load is done (the caller hands `planner` to the cycle), else None."""
        if self._future is None or not self._future.done():
            return None
        future, self._future, self._wanted = self._future, None, None
        if future.cancelled():
            return None
        swap = future.result()
        if not swap.error:
            self.sha256, self.version = swap.update.sha256, swap.update.version
        return swap

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)


def model_version(model: GPModel) -> int:
    """The profile's model version (`gpmppi.gp.online_ground.model_version`)."""
    from gpmppi.gp.online_ground import model_version as version

    return version(model)


def profile_sha256(model_file: str | None) -> str | None:
    """The sha256 of the profile file the planner started with (None: the shipped one, or unreadable)."""
    from gpmppi.gp.profile_store import file_sha256

    try:
        return None if model_file is None else file_sha256(model_file)
    except OSError:
        return None


def take_swap(node: Node, cycle: PlannerCycle, swap: Swap, outputs: Any) -> None:  # outputs: planner.Outputs
    """Plan with a new model version's planner from the next state on (or log why it was not taken)."""
    if swap.error or swap.planner is None or swap.model is None:
        node.error(swap.error)
        return
    cycle.swap_planner(swap.planner, swap.model.terrains)
    outputs.model_version = swap.update.version
    node.log.info("planning with model version %d: grounds %s", swap.update.version, swap.model.terrains)
