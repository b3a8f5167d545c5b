"""Session-wide checks for the whole suite."""

import os
import subprocess
from pathlib import Path

import pytest

import tacsplat  # noqa: F401  (before any test module imports torch: the process-wide defaults it sets must come first)


def pytest_sessionstart(session):
    """Under ``.ci/run`` (TACSPLAT_EXPECT_COLD_CACHE=1): the caches that could stand in for an
    install step or a first computation hold nothing when the tests start."""
    if os.environ.get("TACSPLAT_EXPECT_COLD_CACHE") != "1":
        return
    for var in ("TACSPLAT_CACHE", "NUMBA_CACHE_DIR", "MPLCONFIGDIR"):
        folder = os.environ.get(var)
        if not folder:
            raise pytest.UsageError(f"TACSPLAT_EXPECT_COLD_CACHE=1 but {var} is not set")
        leftovers = [p for p in Path(folder).rglob("*") if p.is_file()] if Path(folder).exists() else []
        if leftovers:
            raise pytest.UsageError(f"{var}={folder} is not empty at the start of the tests: {leftovers[:3]}")


class Mount:
    """A tmpfs mounted for one test (the suite runs as root): ``path``, and :meth:`read_only` to remount it."""

    def __init__(self, path: Path, size: str):
        self.path = path
        self.size = size

    def read_only(self) -> None:
        subprocess.run(["mount", "-o", "remount,ro", str(self.path)], check=True, capture_output=True)

    def writable(self) -> None:
        subprocess.run(["mount", "-o", f"remount,rw,size={self.size}", str(self.path)], check=True, capture_output=True)

    def resize(self, size: str) -> None:
        """Change the size limit (to free space, as a person would, without deleting anything)."""
        self.size = size
        subprocess.run(["mount", "-o", f"remount,size={size}", str(self.path)], check=True, capture_output=True)


@pytest.fixture
def tmpfs(tmp_path):
    """``tmpfs(size="2m") -> Mount``: a size-limited file system of its own, unmounted after the test. Full-disk
    and read-only cases need one: the tests run as root, and ``chmod`` does not stop root."""
    mounts = []

    def make(size: str = "2m", name: str = "mnt") -> Mount:
        if os.geteuid() != 0:
            pytest.skip("mounting a tmpfs needs root")
        path = tmp_path / name
        path.mkdir()
        done = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True, text=True
        )
        if done.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
        mounts.append(path)
        return Mount(path, size)

    yield make
    for path in reversed(mounts):
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


@pytest.fixture(autouse=True)
def _progress_shown():
    """Each test starts with progress shown, whatever an earlier test's ``--quiet`` left in the process."""
    from tacsplat.progress import set_quiet

    set_quiet(False)
