"""``python -m tacsplat``: the same as the ``tacsplat`` command."""

from tacsplat.cli import run

run()
