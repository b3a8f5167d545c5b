"""The command line's words: an empty argument is a value like any other, never part of a command's path; a reader
of stdout that goes away early (``tacsplat ... | head``) ends the command quietly with 141."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from tacsplat.cli import build_parser


@pytest.fixture(scope="module")
def tree():
    return build_parser().tree


@pytest.mark.parametrize("empty", ["", " "])
def test_an_empty_argument_is_handed_to_its_command(tree, empty):
    argv = ["bench", "compare", "a.json", "b.json", "--match", empty]
    assert tree.split_own_options(argv) == (["bench", "compare"], ["a.json", "b.json", "--match", empty])
    argv = ["bench", "paper", "--out", "x", "--objects", empty, "-v"]
    assert tree.split_own_options(argv) == (["bench", "paper", "--verbose"], ["--out", "x", "--objects", empty])


@pytest.mark.parametrize(
    "argv, chosen",
    [
        (["--log-level", "warning", "bench", "paper", "--out", "b"], ("bench paper", 4)),  # an option's value
        (["--log-level=warning", "-v", "bench", "compare"], ("bench compare", 4)),
        (["bench", "compare", "bench", "compare"], ("bench compare", 2)),  # a value that names a command
        (["bench", "nothing", "compare"], ("bench", 1)),  # a word that names no command ends the path
        (["", "bench", "compare"], ("bench compare", 3)),
    ],
)
def test_the_command_path_ends_at_the_first_word_that_does_not_extend_it(tree, argv, chosen):
    assert tree._chosen(argv) == chosen


def test_a_reader_that_closes_stdout_early_ends_the_command_quietly(tmp_path):
    for name, factor in (("a", 1), ("b", 2)):  # a comparison of some 600 kB: more than any pipe buffer holds
        (tmp_path / f"{name}.json").write_text(json.dumps({f"k{i}": factor * i for i in range(20000)}))
    argv = [sys.executable, "-m", "tacsplat", "bench", "compare", str(tmp_path / "a.json"), str(tmp_path / "b.json")]
    read, write = os.pipe()
    os.close(read)  # the reader has gone before the first line
    try:
        done = subprocess.run(argv, stdout=write, stderr=subprocess.PIPE, text=True, timeout=60)
    finally:
        os.close(write)
    assert done.returncode == 141 and done.stderr == "", (done.returncode, done.stderr)
