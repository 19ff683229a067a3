"""Saving and taking a learned robot profile: written atomically, named by its bytes' sha256.

`GPModel.save` writes a temporary file in the profile's folder, fsyncs it and renames it over the profile
(`os.replace`): a failed write (a full disk) or a crash mid-save leaves the old profile as it was, byte for byte.
`save_profile` adds the folder's fsync (so the rename itself survives a power cut) and returns the new file's sha256,
which the `ModelUpdate` message carries; `load_checked` refuses a file whose bytes are not the announced ones (a later
save replaced it, or it was copied half) in one line.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from gpmppi.gp.model_file import GPModel, ModelFileError


def file_sha256(path: str | os.PathLike) -> str:
    """The hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def save_profile(model: GPModel, path: str | os.PathLike) -> str:
    """Write `model` to `path` atomically (see the module docstring); its sha256. An OSError (e.g. no space left)
    propagates with the old file intact and no temporary file left."""
    path = Path(path)
    model.save(path)
    try:
        fd = os.open(path.parent, os.O_RDONLY)
    except OSError:  # a folder that cannot be opened (some file systems): the rename is done, just not fsynced
        fd = None
    if fd is not None:
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    return file_sha256(path)


def load_checked(path: str | os.PathLike, sha256: str | None = None) -> GPModel:
    """Load a profile; ModelFileError (one line) when its bytes' sha256 is not `sha256` (None: not checked)."""
    if sha256 is not None:
        try:
            actual = file_sha256(path)
        except OSError as e:
            raise ModelFileError(f"{path}: cannot read the announced profile ({e.strerror or e})") from e
        if actual != sha256:
            raise ModelFileError(f"{path}: sha256 {actual[:12]}... is not the announced {sha256[:12]}... (the file was "
                                 "replaced since); waiting for the next model update")
    return GPModel.load(path)
