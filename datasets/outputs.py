"""Output folders that every writing command claims the same way: created, writable, locked.

``claim_output_dir`` is the one entry for a command's ``--out`` (or positional
output) folder: it creates the folder and its parents, proves it writable, and
takes an exclusive lock held until the returned :class:`OutputLock` is
released (or the process dies), so two commands never write one folder at once.
Each failure is one :class:`ConfigError` naming the option and the path. The
lock file holds the PID of the process writing the folder (also of a
:class:`~tacsplat.datasets.SceneWriter`, which locks its journal), so a refusal
names that process.
"""

from __future__ import annotations

import fcntl
import os
import time
from contextlib import AbstractContextManager
from pathlib import Path

from tacsplat.errors import ConfigError, StorageError
from tacsplat.files import check_writable

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
    if not os.access(path, os.W_OK | os.X_OK) and not os.statvfs(path).f_flag & os.ST_RDONLY:
        raise ConfigError(option, f"{path} is not writable")
    try:
        check_writable(path)  # read-only or full: refused before any work, not after it
    except StorageError as exc:
        raise ConfigError(option, str(exc)) from None
    return path


def record_writer(path: Path) -> None:
    """Write this process's PID into ``path``'s lock file, for :func:`other_writer` to name it."""
    try:
        (Path(path) / LOCK_NAME).write_text(f"{os.getpid()}\n")
    except OSError:
        pass  # a full or read-only disk: the PID only makes a refusal's message more precise


def other_writer(path: Path, wait_s: float = 1.0) -> str:
    """The process writing ``path`` as a message names it: "another tacsplat process (PID n)", the PID its lock
    file holds. The holder records it just after taking the lock, so a file without one is read again for up to
    ``wait_s`` (the PID is left out when it never comes: a full disk)."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            return f"another tacsplat process (PID {int((Path(path) / LOCK_NAME).read_text().split()[0])})"
        except (OSError, ValueError, IndexError):
            if time.monotonic() >= deadline:
                return "another tacsplat process"
            time.sleep(0.02)


class OutputLock(AbstractContextManager):
    """An exclusive lock on an output folder (``.tacsplat.lock`` inside it); a context manager."""

    def __init__(self, path: Path, option: str):
        self.path = path
        self._file = (path / LOCK_NAME).open("a")
        try:
            fcntl.flock(self._file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self._file.close()
            raise ConfigError(
                option, f"{path} is being written by {other_writer(path)}; wait for it to end or choose another folder"
            ) from None
        record_writer(path)

    def release(self) -> None:
        if not self._file.closed:
            self._file.close()

    def __exit__(self, *exc) -> None:
        self.release()


def claim_output_dir(path: str | Path, option: str = "--out") -> OutputLock:
    """Create, check and lock an output folder; release the returned lock when the command ends."""
    return OutputLock(ensure_output_dir(path, option), option)
