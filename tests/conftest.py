"""Session-wide checks for the whole suite."""

import os
from pathlib import Path

import pytest


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
