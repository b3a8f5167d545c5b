"""The datasets commands' option values out of range are usage errors (exit 2) naming the option; `inspect` finds a
twin capture missing its ground truth, and ground truth the index lost behind its journal."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from tacsplat.cli import main
from tacsplat.datasets import SceneMeta, SceneWriter, check_scene
from tacsplat.datasets.inspect import run_inspect


@pytest.mark.parametrize(
    "command, option, words",
    [
        (["import", "blender", "SRC", "--scale", "0"], "--scale", "must be a finite positive number"),
        (
            ["import", "colmap", "SRC", "--images", "IMG", "--scale", "nan"],
            "--scale",
            "must be a finite positive number",
        ),
        (
            ["import", "colmap", "SRC", "--images", "IMG", "--test-every", "-1"],
            "--test-every",
            "must be an integer >= 0",
        ),
        (["import", "nerfstudio", "SRC", "--scale", "-2"], "--scale", "must be a finite positive number"),
        (["import", "nerfstudio", "SRC", "--test-every", "-3"], "--test-every", "must be an integer >= 0"),
    ],
)
def test_import_values_out_of_range_are_usage_errors(tmp_path, capsys, command, option, words):
    out = tmp_path / "scene"
    args = [str(tmp_path / a) if a in ("SRC", "IMG") else a for a in command]
    assert main([*args, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    prog = "tacsplat " + " ".join(command[:2])
    assert err.startswith(f"{prog}: error: {option}: {words}") and "--help" in err, err
    assert not out.exists()


def test_inspect_plot_in_a_format_that_cannot_be_written_is_a_usage_error(scene_dir, tmp_path, capsys):
    assert main(["inspect", str(scene_dir), "--plot", str(tmp_path / "p.xyz")]) == 2
    captured = capsys.readouterr()
    assert "tacsplat inspect: error: --plot: cannot save a picture as .xyz; use one of " in captured.err
    assert ".png" in captured.err and captured.out == "" and not (tmp_path / "p.xyz").exists()


def _twin_capture(path, h, gt_mesh: bool = True, test_depth: bool = True):
    """A scene as a capture on the twin records it (``extra.simulator``): a train view and a test view."""
    meta = SceneMeta("sim", "ball", {}, {"simulator": "mujoco 3"})
    with SceneWriter.create(path, h.intrinsics(), meta) as writer:
        writer.add_frame(h.frame_image(0), h.ring_pose(0))
        depth = np.full((h.HEIGHT, h.WIDTH), 0.4, np.float32) if test_depth else None
        writer.add_frame(h.frame_image(1), h.ring_pose(1), split="test", gt_depth=depth)
        if gt_mesh:
            writer.set_gt_mesh(trimesh.creation.icosphere(subdivisions=1, radius=0.05))
    return path


def test_a_twin_capture_without_its_ground_truth_is_a_problem(tmp_path, h, capsys):
    assert check_scene(_twin_capture(tmp_path / "whole", h))[1] == []
    no_mesh = _twin_capture(tmp_path / "no-mesh", h, gt_mesh=False)
    assert run_inspect(no_mesh) == 1
    out = capsys.readouterr().out
    assert f"{no_mesh / 'scene.json'} [gt.mesh]: a capture on the twin without its ground-truth mesh" in out
    assert "--resume" in out
    _, problems = check_scene(_twin_capture(tmp_path / "no-depth", h, test_depth=False))
    assert [(p.field, "test frame(s) 1" in str(p)) for p in problems] == [("gt.depth", True)]
    # a scene of the same source that no twin captured (tests, imports) need not hold ground truth
    assert check_scene(h.build_scene(tmp_path / "other", gt=False))[1] == []


def test_ground_truth_the_journal_holds_and_the_index_lost_is_a_problem(tmp_path, h):
    path = _twin_capture(tmp_path / "s", h)
    index = path / "scene.json"
    data = json.loads(index.read_text())
    data["gt"]["depth"] = {}  # as when the writer stopped after journaling the frame, before rewriting scene.json
    index.write_text(json.dumps(data))
    _, problems = check_scene(path)
    assert [p.field for p in problems] == ["gt"], problems
    assert "records other ground truth than scene.json holds" in str(problems[0]) and "resum" in str(problems[0])
    SceneWriter.resume(path).close()
    assert check_scene(path)[1] == []
