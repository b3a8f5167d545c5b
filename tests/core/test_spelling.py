"""Identifiers spell ``color`` (as gsplat's ``colors=`` does), never ``colour``; prose may use either."""

from __future__ import annotations

import io
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FOLDERS = ("tacsplat", "drivers", "sim", "acquisition", "reconstruction", "datasets", "tests")


def british_names(source: str) -> list[tuple[int, str]]:
    return [
        (t.start[0], t.string)
        for t in tokenize.generate_tokens(io.StringIO(source).readline)
        if t.type == tokenize.NAME and "colour" in t.string.lower()
    ]


def test_the_check_finds_a_british_name_and_not_prose():
    assert british_names("colour_weight = 1  # a colour\n'colour'\n") == [(1, "colour_weight")]


def test_identifiers_spell_color():
    found = [
        f"{path.relative_to(ROOT)}:{line}: {name}"
        for folder in FOLDERS
        for path in sorted((ROOT / folder).rglob("*.py"))
        for line, name in british_names(path.read_text())
    ]
    assert not found, "spell these color:\n" + "\n".join(found)
