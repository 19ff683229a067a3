"""Where a run's output files go, decided before anything starts: a recording never overwrites.

`resolve_output` turns what the user gave (`--record PATH`, `--rerun save PATH`) into the file that will be
written, and says why when that is not the path as given:

- an existing folder: a new file inside it, `run-YYYYmmdd-HHMMSS.mcap`;
- an existing file (or an earlier recording's rotated or restart parts under that name): the next free
  suffixed name, `run-1.mcap`, `run-2.mcap`, ...; the earlier file stays as it was;
- a folder that does not exist, or one this process cannot write to: a one-line `OutputPathError` (a
  `ValueError`) that names the path and what to do; folders are not created behind the user's back.

The writers refuse an existing file too (they create theirs exclusively: `services.recording.mcap_writer.McapWriter`,
the viewer's .rrd), so a file that appears between this check and the start is not overwritten either.
"""

from __future__ import annotations

import glob
import os
import time
from pathlib import Path


class OutputPathError(ValueError):
    """An output path that cannot be written; the message is one line naming the path and what to do."""


def _siblings(path: Path) -> list[Path]:
    """The parts a writer would add next to `path`: rotated `<stem>_001<suffix>`, restarted
    `<stem>.restart1<suffix>` (services.recording.mcap_io, services.launch.supervisor)."""
    stem, suffix = glob.escape(path.stem), glob.escape(path.suffix)
    folder = path.parent
    return [*folder.glob(f"{stem}_[0-9][0-9][0-9]{suffix}"), *folder.glob(f"{stem}.restart*{suffix}")]


def taken(path: Path) -> bool:
    """True when writing `path` would meet an earlier file: the file itself or one of its parts."""
    return path.exists() or path.is_symlink() or bool(_siblings(path))


def free_name(path: str | Path, limit: int = 10_000) -> Path:
    """`path` if nothing of that name exists, else `<stem>-1<suffix>`, `<stem>-2<suffix>`, ... (the first free)."""
    path = Path(path)
    if not taken(path):
        return path
    for n in range(1, limit):
        candidate = path.with_name(f"{path.stem}-{n}{path.suffix}")
        if not taken(candidate):
            return candidate
    raise OutputPathError(f"{path}: {limit} files of that name exist already; choose another name")


def resolve_output(path: str | Path, suffix: str = ".mcap", now: float | None = None) -> tuple[Path, str]:
    """(the file to write, a note saying why it differs from `path`, or "").

    Raises `OutputPathError` (one line) when the folder does not exist, is not a folder, or is not writable."""
    given = str(path)
    p = Path(path).expanduser()
    if p.is_dir():
        stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now))
        folder, candidate = p, p / f"run-{stamp}{suffix}"
        note = f"{given} is a folder: writing a new file inside it"
    elif given.endswith(("/", os.sep)):
        raise OutputPathError(f"cannot write into {given}: no such folder; create it first (mkdir -p {given})")
    else:
        folder, candidate, note = p.parent, p, ""
        if not folder.exists():
            raise OutputPathError(
                f"cannot write {given}: its folder {folder} does not exist; create it first (mkdir -p {folder}) "
                "or give a path in an existing folder"
            )
        if not folder.is_dir():
            raise OutputPathError(f"cannot write {given}: {folder} is not a folder; give a path in a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputPathError(f"cannot write {given}: the folder {folder} is not writable here; give another path")
    chosen = free_name(candidate)
    if chosen != candidate:
        why = f"{candidate} exists and is kept"
        note = f"{note}; {why}" if note else why
    if note:
        note = f"{note}: writing {chosen}"
    return chosen, note


def create_exclusive(path: str | Path) -> None:
    """Create `path` empty, failing with FileExistsError if anything is there (O_EXCL): a writer's claim on
    its file before it opens it."""
    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))
