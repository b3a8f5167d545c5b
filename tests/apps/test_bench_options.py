"""The benches' options: a value no run could use (repeated, out of a capture's or a training's range) is one
usage error (exit 2) naming the option, before anything is made."""

from __future__ import annotations

import pytest

from tacsplat.cli import main

PAPER = ["--objects", "teapot", "--settings", "minimal", "--methods", "3dgs", "--resolution", "32", "--test-views", "2"]
TOUCHES = ["--touches", "0,4", "--seeds", "0", "--resolution", "32"]


@pytest.mark.parametrize(
    "command, option, message",
    [
        (["bench", "paper", *PAPER, "--seeds", "0,0"], "--seeds", "0 is given twice"),
        (["bench", "paper", *PAPER, "--objects", "teapot,teapot"], "--objects", "two objects are named 'teapot'"),
        (["bench", "paper", *PAPER, "--methods", "3dgs,paper,3dgs"], "--methods", "'3dgs' is given twice"),
        (["bench", "paper", *PAPER, "--settings", "minimal,minimal"], "--settings", "'minimal' is given twice"),
        (["bench", "touches", *TOUCHES, "--touches", "4,4"], "--touches", "4 is given twice"),
        (["bench", "touches", *TOUCHES, "--seeds", "1,0,1"], "--seeds", "1 is given twice"),
        (["bench", "scaling", "--resolutions", "32,32", "--steps", "20"], "--resolutions", "32 is given twice"),
        (["bench", "scaling", "--resolutions", "32", "--steps", "20,20"], "--steps", "20 is given twice"),
        (["bench", "scaling", "--methods", "3dgs,3dgs", "--resolutions", "32"], "--methods", "'3dgs' is given twice"),
    ],
)
def test_a_repeated_value_is_a_usage_error(tmp_path, capsys, command, option, message):
    out = tmp_path / "out"
    assert main([*command, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"error: {option}: {message}" in err and "Traceback" not in err and not out.exists(), err


def test_two_mesh_files_of_one_name_are_a_usage_error(tmp_path, capsys):
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "cup.obj").write_text("v 0 0 0\n")
    objects = f"{tmp_path / 'a' / 'cup.obj'},{tmp_path / 'b' / 'cup.obj'}"
    assert main(["bench", "paper", "--out", str(tmp_path / "out"), *PAPER, "--objects", objects]) == 2
    assert "error: --objects: two objects are named 'cup'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "command, option",
    [
        (["bench", "paper", *PAPER, "--seeds", "-1"], "--seeds"),
        (["bench", "paper", *PAPER, "--resolution", "4"], "--resolution"),
        (["bench", "paper", *PAPER, "--downscale", "0"], "--downscale"),
        (["bench", "touches", *TOUCHES, "--seeds", "-1"], "--seeds"),
        (["bench", "scaling", "--object", "nope", "--resolutions", "32", "--steps", "20"], "--object"),
        (["bench", "step", "--object", "nope", "--resolutions", "32", "--iterations", "20"], "--object"),
        (["bench", "scaling", "--resolutions", "32", "--steps", "0"], "--steps"),
        (["bench", "scaling", "--resolutions", "4", "--steps", "20"], "--resolutions"),
        (["demo", "--resolution", "4"], "--resolution"),
    ],
)
def test_a_value_a_capture_or_training_refuses_is_a_usage_error_before_anything_runs(tmp_path, capsys, command, option):
    out = tmp_path / "out"
    assert main([*command, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"error: {option}: " in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_downscale_without_a_dataset_is_a_usage_error(tmp_path, capsys):
    """Before: the twin's runs trained at half size while report.md said the full --resolution."""
    out = tmp_path / "out"
    assert main(["bench", "paper", *PAPER, "--downscale", "2", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "error: --downscale: " in err and "--dataset" in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


@pytest.mark.parametrize("option", ["--objects", "--methods", "--settings"])
@pytest.mark.parametrize("value", ["", " , "])
def test_a_list_that_names_nothing_is_a_usage_error_not_every_object(tmp_path, capsys, option, value):
    out = tmp_path / "out"
    assert main(["bench", "paper", *PAPER, option, value, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"error: {option}: names nothing" in err and not out.exists(), err


@pytest.mark.parametrize(
    "command, option",
    [
        (["bench", "rasterizer", "--repeats", "0", "--sizes", "8x8:10"], "--repeats"),
        (["bench", "rasterizer", "--sizes", "16x16:-5"], "--sizes"),
        (["bench", "rasterizer", "--sizes", "0x0:0"], "--sizes"),
        (["bench", "rasterizer", "--json", "{tmp}", "--sizes", "8x8:10", "--skip-torch"], "--json"),
        (["bench", "gpu", "--out", "{tmp}/g", "--methods", ",", "--device", "cpu"], "--methods"),
        (["bench", "gpu", "--out", "{tmp}/g", "--parity-seeds", ",", "--device", "cpu"], "--parity-seeds"),
        (["bench", "gpu", "--out", "{tmp}/g", "--steps", "0", "--device", "cpu"], "--steps"),
        (["bench", "gpu", "--out", "{tmp}/g", "--prepare", "{tmp}/file.txt"], "--prepare"),
        (["bench", "gpu", "--out", "{tmp}/g", "--parity", "{tmp}/none"], "--parity"),
        (["bench", "scaling", "--out", "{tmp}/s", "--resolutions", ","], "--resolutions"),
        (["bench", "scaling", "--out", "{tmp}/s", "--steps", ","], "--steps"),
    ],
)
def test_an_empty_list_or_a_count_below_one_is_a_usage_error_before_any_work(tmp_path, capsys, command, option):
    """Before: tracebacks (an empty list indexed, negative tensor sizes, a folder written as a file), or a bench that
    started its capture, or exit 0 with an empty report."""
    (tmp_path / "file.txt").write_text("x\n")
    assert main([arg.replace("{tmp}", str(tmp_path)) for arg in command]) == 2
    err = capsys.readouterr().err
    assert f"error: {option}: " in err and "Traceback" not in err, err
    assert not (tmp_path / "g").exists() and not (tmp_path / "s").exists()
