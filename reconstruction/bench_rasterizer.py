"""`tacsplat bench rasterizer` (filled in by the rasterizer work)."""

from __future__ import annotations


def register(cli) -> None:
    """Add `bench rasterizer` (none yet)."""
