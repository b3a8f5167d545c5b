"""Command-line option values shared by the applications."""

from __future__ import annotations

from tacsplat.errors import UsageError


def comma_separated_ints(text: str, option: str) -> tuple[int, ...]:
    """The integers of an option like ``--seeds 0,1,2``; a UsageError (exit 2) naming ``option`` otherwise."""
    try:
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise UsageError(option, f"expected comma-separated integers, got {text!r}") from None
