"""Output folders that every writing command claims the same way: created, writable, locked.

``claim_output_dir`` is the one entry for a command's ``--out`` (or positional
output) folder: it creates the folder and its parents, proves it writable, and
takes an exclusive lock held until the returned :class:`OutputLock` is
released (or the process dies), so two commands never write one folder at once.
Each failure is one :class:`ConfigError` naming the option and the path.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from tacsplat.errors import ConfigError

LOCK_NAME = ".tacsplat.lock"


def ensure_output_dir(path: str | Path, option: str = "--out") -> Path:
    """Create ``path`` (and its parents) as a writable folder; a ConfigError naming ``option`` otherwise."""
    path = Path(path)
    for parent in [path, *path.parents]:
        if parent.exists() and not parent.is_dir():
            what = "is a file" if parent == path else f"is inside {parent}, which is a file"
            raise ConfigError(option, f"{path} {what}; choose a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(option, f"cannot create {path}: {exc.strerror or exc}") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise ConfigError(option, f"{path} is not writable")
    return path


class OutputLock:
    """An exclusive lock on an output folder (``.tacsplat.lock`` inside it); a context manager."""

    def __init__(self, path: Path, option: str):
        self.path = path
        self._file = (path / LOCK_NAME).open("a")
        try:
            fcntl.flock(self._file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self._file.close()
            raise ConfigError(option, f"{path} is being written by another tacsplat process; wait for it or "
                              "choose another folder") from None

    def release(self) -> None:
        if not self._file.closed:
            self._file.close()

    def __enter__(self) -> "OutputLock":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def claim_output_dir(path: str | Path, option: str = "--out") -> OutputLock:
    """Create, check and lock an output folder; release the returned lock when the command ends."""
    return OutputLock(ensure_output_dir(path, option), option)
