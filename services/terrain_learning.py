"""The terrain service's learner shell: runs a new ground's fit in a separate process and swaps the model when it is in.

The fit (gpmppi/gp/online_ground.py, 10-20 s of numpy on one core) runs in a child process started with `spawn` (never
a fork of a process with a Zenoh session) at a lower CPU priority (nice 10), so it cannot hold the terrain service's
loop (no GIL shared) nor take a core from the planner ahead of it. The child saves the profile atomically
(gpmppi/gp/profile_store.py), keeps the steps it learned from beside it as a log (`gpmppi train` refits the ground
from it together with other logs), and returns the profile's path and sha256; the service then loads it back (what
the planner will load), builds the estimator over the new grounds and publishes a `ModelUpdate`.
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from schemas import ModelUpdate

if TYPE_CHECKING:
    from gpmppi.gp.model_file import GPModel
    from gpmppi.terrain.learning import FitJob, GroundLearning


@dataclass
class FitOutcome:
    """What a fit gave: the saved profile (path, sha256, grounds) and the report line, or the reason it made none."""

    path: str = ""
    sha256: str = ""
    grounds: tuple[str, ...] = ()
    learned: str = ""
    samples: int = 0
    message: str = ""
    error: str = ""  # set: no ground was added (too little data, a failed save); the message says why


def _lower_priority() -> None:
    try:
        os.nice(10)
    except OSError:
        pass


def steps_log_path(profile: str | Path, ground: str) -> Path:
    """Where the steps a ground was learned from are kept: beside the profile, `<profile stem>.<ground>.mcap`."""
    p = Path(profile)
    return p.with_name(f"{p.stem}.{ground}.mcap")


def write_steps_log(path: Path, steps: np.ndarray, ground: str, robot: str, dt: float) -> None:
    """The learned ground's steps as a log `gpmppi train` reads (state, cmd and terrain/label of `robot`): each step
    a segment of its own (its state and command at t, its next state at t + dt, then a gap), so no step is paired
    with another. Written to a temporary file and renamed: never half there."""
    from schemas import Command, Header, State, TerrainLabel
    from services.recording.mcap_writer import McapWriter

    tick = round(dt * 1e9)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with McapWriter(tmp) as w:
            for k, row in enumerate(np.asarray(steps, dtype=np.float64)):
                t = (1 + 4 * k) * tick
                for stamp, x in ((t, row[:5]), (t + tick, row[7:])):
                    h = Header(stamp_ns=stamp)
                    w.write(f"gpmppi/{robot}/state", State(header=h, x=x[0], y=x[1], theta=x[2], v=x[3], omega=x[4]))
                    w.write(f"gpmppi/{robot}/terrain/label", TerrainLabel(header=h, terrain=ground))
                w.write(f"gpmppi/{robot}/cmd", Command(header=Header(stamp_ns=t), v_ref=row[5], omega_ref=row[6]))
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a full disk leaves no half log behind
        raise


def run_fit(job: FitJob, path: str) -> FitOutcome:
    """In the child: learn the ground, save the profile to `path` atomically (the old file stays on any error), and
    the steps it was learned from beside it (`steps_log_path`) for `gpmppi train`."""
    from gpmppi.gp.online_ground import TooLittleData, learn_ground
    from gpmppi.gp.profile_store import save_profile

    base = job.profile()
    try:
        model, report = learn_ground(base, job.samples(), job.name, job.settings)
    except TooLittleData as e:
        return FitOutcome(learned=job.name, samples=len(job.x), error=str(e))
    model.made_by = (f"{base.made_by or 'a robot profile'}; ground {job.name!r} learned online from "
                     f"{len(job.x)} steps")
    log = steps_log_path(path, job.name)
    try:
        if job.steps is not None:
            write_steps_log(log, job.steps, job.name, model.robot, model.dt)
        sha = save_profile(model, path)
    except OSError as e:
        if job.steps is not None:  # the steps of a ground the profile did not gain: not left for `gpmppi train`
            log.unlink(missing_ok=True)
        return FitOutcome(learned=job.name, samples=len(job.x),
                          error=f"learned ground {job.name!r} not saved to {path}: {e.strerror or e}; the profile "
                          "there is unchanged")
    return FitOutcome(path, sha, tuple(model.terrains), job.name, len(job.x), report.line())


def _child(job: FitJob, path: str, conn: Connection) -> None:
    """The fit process: lower priority, fit and save, send the outcome back."""
    _lower_priority()
    try:
        conn.send(run_fit(job, path))
    finally:
        conn.close()


class Learner:
    """Runs `GroundLearning`'s fit jobs in a child process and hands back the saved model when one is in."""

    def __init__(self, learning: GroundLearning, path: str | None, version: int = 0) -> None:
        self.learning = learning
        self.path = path  # where the learned profile goes (None: nowhere; a request is refused)
        self.version = version
        self._process: BaseProcess | None = None
        self._conn: Connection | None = None
        self._done: list[BaseProcess] = []  # finished fits not yet reaped
        self._pool: ThreadPoolExecutor | None = None
        self._loading: Future[tuple[GPModel | None, ModelUpdate | None, str | None]] | None = None

    def submit_ready(self) -> str | None:
        """Start the fit when the collection is complete; the log line, else None."""
        if self._process is not None or (job := self.learning.take_job()) is None:
            return None
        assert self.path is not None
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe(duplex=False)
        self._process = ctx.Process(target=_child, args=(job.for_process(), self.path, child), name="ground-fit",
                                    daemon=True)
        self._process.start()
        child.close()
        return f"fitting ground {job.name!r} from {len(job.x)} steps in the background"

    def _outcome(self) -> FitOutcome | None:
        """The child's outcome once it is done (None while it runs)."""
        assert self._process is not None and self._conn is not None
        if self._conn.poll():
            try:
                out = self._conn.recv()
            except (EOFError, OSError) as e:
                out = FitOutcome(learned=self.learning.name, error=f"the fit of {self.learning.name!r} failed: {e!r}")
        elif self._process.is_alive():
            return None
        else:
            out = FitOutcome(learned=self.learning.name, error=f"the fit of {self.learning.name!r} ended with exit "
                             f"code {self._process.exitcode} and no result; the profile is unchanged")
        # not joined here: the child's interpreter teardown takes a second or more, which would hold the loop; it
        # is a daemon that exits on its own, reaped by a later `_outcome` or at `close`
        self._done.append(self._process)
        self._conn.close()
        self._process = self._conn = None
        return out

    def poll(self) -> tuple[GPModel | None, ModelUpdate | None, str | None]:
        """(the new model, its update message, a log line) once a fit is in and its profile loaded back; (None, None,
        error line) for a fit that added nothing; (None, None, None) while none is done. The saved profile is loaded
        on a thread (a second or two of reading and decoding that would otherwise hold the terrain loop)."""
        if self._loading is not None:
            if not self._loading.done():
                return None, None, None
            loading, self._loading = self._loading, None
            model, msg, line = loading.result()
            if model is None or msg is None:
                self.learning.failed()
            else:  # here, on the loop's thread, like every other change of the learning's state
                self.learning.finished(model)
                self.version = msg.version
            return model, msg, line
        self._done = [p for p in self._done if p.is_alive()]  # is_alive reaps an exited child
        if self._process is None or (out := self._outcome()) is None:
            return None, None, None
        if out.error:
            self.learning.failed()
            return None, None, out.error
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ground-load")
        self._loading = self._pool.submit(self._load, out)
        return None, None, None

    def _load(self, out: FitOutcome) -> tuple[GPModel | None, ModelUpdate | None, str | None]:
        from gpmppi.gp.model_file import ModelFileError
        from gpmppi.gp.online_ground import model_version
        from gpmppi.gp.profile_store import load_checked

        try:
            model = load_checked(out.path, out.sha256)
        except ModelFileError as e:
            return None, None, str(e)
        msg = ModelUpdate(version=model_version(model), path=str(out.path), sha256=out.sha256,
                          grounds=list(out.grounds), learned=out.learned, samples=out.samples, message=out.message)
        return model, msg, out.message

    def close(self) -> None:
        """Stop a fit still running (the service is stopping: its save is atomic, the old profile stays)."""
        if self._process is not None and self._process.is_alive():
            self._process.terminate()
            self._process.join(5.0)
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
