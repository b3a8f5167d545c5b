"""`tacsplat` subcommands of tacsplat.acquisition (see tacsplat.cli)."""

from __future__ import annotations


def register(cli) -> None:
    """Add this package's commands to the tree (none yet)."""
