"""Writing files so that a full disk, a read-only mount or a crash never leaves a half-written file.

Every file tacsplat writes goes through :func:`atomic_write` (or :func:`atomic_file`): the data goes to a
temporary sibling that is renamed over the target only once it is complete, so the target is always either
the old file or the new one. Any failure removes the temporary file and, for the reasons a user can fix
(disk full, read-only, permission), raises one :class:`~tacsplat.errors.StorageError` naming the file.
"""

from __future__ import annotations

import errno
import os
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

from tacsplat.errors import ConfigError, StorageError, UsageError

# errno -> what a person should be told; anything else keeps the operating system's words
_REASONS = {
    errno.ENOSPC: "the disk is full (no space left on device): free space and run the command again (with "
    "--resume where it has one: what was written before is kept)",
    errno.EDQUOT: "the disk quota is exceeded: free space and run the command again (with --resume where it has one)",
    errno.EROFS: "the file system is read-only: write to another folder",
    errno.EACCES: "permission denied: write to another folder",
    errno.EPERM: "operation not permitted: write to another folder",
    errno.EFBIG: "the file is too large for this file system",
}


def storage_error(exc: OSError, path: str | Path) -> StorageError:
    """The :class:`StorageError` for ``exc`` (an OSError raised while writing ``path``)."""
    return StorageError(path, _REASONS.get(exc.errno) or f"cannot write: {exc.strerror or exc}")


def is_storage_failure(exc: BaseException) -> bool:
    """Whether ``exc`` is an OSError a person fixes on the storage side (full, read-only, permission)."""
    return isinstance(exc, OSError) and exc.errno in _REASONS


def default_temp(path: Path) -> Path:
    """The temporary sibling ``path`` is written to before its rename: ``name.tmp``."""
    return path.with_name(path.name + ".tmp")


def fsync_dir(directory: Path) -> None:
    """Make a rename in ``directory`` durable (where the file system can)."""
    with suppress(OSError):  # a directory that cannot be opened, or a file system that does not sync directories
        fd = os.open(directory, os.O_RDONLY)  # (tmpfs, network mounts): the rename itself is done
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextmanager
def atomic_file(path: str | Path, temp: Path | None = None, fsync: bool = True) -> Iterator[BinaryIO]:
    """``with atomic_file(path) as f: f.write(...)``: ``f`` is the temporary file, renamed over ``path`` when the
    block ends without an exception. On any failure the temporary file is removed, ``path`` is untouched, and an
    OSError of the storage (full, read-only, permission) becomes a StorageError naming ``path``."""
    path = Path(path)
    tmp = Path(temp) if temp is not None else default_temp(path)
    try:
        try:
            with open(tmp, "wb") as f:
                yield f
                f.flush()
                if fsync:
                    os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            with suppress(OSError):  # a read-only file system: nothing was created either
                tmp.unlink(missing_ok=True)
            raise
    except OSError as exc:
        raise storage_error(exc, path) from None
    if fsync:
        fsync_dir(path.parent)


def atomic_write(
    path: str | Path, data: bytes | Callable[[BinaryIO], None], temp: Path | None = None, fsync: bool = True
) -> Path:
    """Write ``data`` (bytes, or a function that writes to a binary file) to ``path`` atomically; returns ``path``.
    See :func:`atomic_file` for what a failure leaves."""
    with atomic_file(path, temp, fsync) as f:
        if callable(data):
            data(f)
        else:
            f.write(data)
    return Path(path)


def check_writable(directory: str | Path) -> None:
    """Refuse, before any work, a folder that cannot take a new file (read-only, no permission, or full):
    creates and removes a small probe file. The folder is created if missing."""
    directory = Path(directory)
    probe = directory / f".tacsplat-write-probe.{os.getpid()}.tmp"  # a temporary file, to a folder's other readers
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with open(probe, "wb") as f:
            f.write(b"\0" * 4096)
            f.flush()
            os.fsync(f.fileno())
    except OSError as exc:
        raise storage_error(exc, directory) from None
    finally:
        with suppress(OSError):
            probe.unlink(missing_ok=True)


def _nearest_existing(path: Path) -> Path:
    """``path`` or the nearest folder above it that exists (an unreadable one counts as missing)."""
    return next(p for p in (path, *path.parents) if os.path.exists(p))


def check_out_folder(option: str, file: str | Path) -> None:
    """Refuse, before any work, the folder of the output ``file`` (the value of ``option``): a UsageError when it,
    or a folder above it, is a file; else :func:`check_writable` on the nearest existing one. Nothing is created:
    the writer makes the folders a new path names."""
    existing = _nearest_existing(Path(file).parent)
    if not existing.is_dir():
        raise UsageError(option, f"{existing} is not a folder")
    check_writable(existing)


def refuse_unwritable(option: str, value) -> None:
    """A ConfigError naming ``option`` when the path ``value`` (None or "": nothing) would land on a read-only or full
    file system: checked before a command's work, so that none runs for minutes only to fail at its first write."""
    if not isinstance(value, (str, os.PathLike)) or not str(value):
        return
    try:
        fs = os.statvfs(_nearest_existing(Path(value).absolute()))
    except OSError:
        return  # (the command reports what it cannot reach)
    full = fs.f_blocks > 0 and fs.f_bfree == 0  # (a pseudo file system, /proc, has no blocks at all: not full)
    if (failure := errno.EROFS if fs.f_flag & os.ST_RDONLY else errno.ENOSPC if full else None) is not None:
        raise ConfigError(option, str(storage_error(OSError(failure, os.strerror(failure)), value)))
