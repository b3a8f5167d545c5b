"""A damaged ground-truth mesh is a problem `inspect` names (not "problems none") and one error of `view`, and a
run's damaged exported mesh is left out of its view with a warning naming it."""

from __future__ import annotations

import logging
import types

import pytest

from tacsplat.cli import main
from tacsplat.datasets import SceneMeta, SceneWriter
from tacsplat.datasets.reader import check_scene


@pytest.fixture
def gt_scene(tmp_path, h):
    import trimesh

    path = tmp_path / "scene"
    meta = SceneMeta(source="sim", object="test-object", capture_plan={"views": 2})
    with SceneWriter.create(path, h.intrinsics(), meta, h.SENSOR) as writer:
        for i in range(2):
            writer.add_frame(h.frame_image(i), h.ring_pose(i), split=("train", "test")[i])
        writer.set_gt_mesh(trimesh.creation.icosphere(subdivisions=2, radius=0.05))
    return path


@pytest.mark.parametrize("keep", [0.5, 0.02])
def test_a_truncated_gt_mesh_is_a_problem_naming_it(gt_scene, keep, capsys):
    mesh = gt_scene / "gt" / "mesh.ply"
    assert check_scene(gt_scene)[1] == []
    data = mesh.read_bytes()
    mesh.write_bytes(data[: int(len(data) * keep)])
    scene, problems = check_scene(gt_scene)
    assert scene is not None and scene.gt_mesh_file is None  # (the rest is still read)
    assert len(problems) == 1 and "gt/mesh.ply" in str(problems[0]), problems
    assert main(["inspect", str(gt_scene)]) == 1
    assert "problems  1" in capsys.readouterr().out


def test_view_of_a_scene_with_a_truncated_gt_mesh_is_one_error_naming_it(gt_scene, tmp_path, capsys):
    pytest.importorskip("viser")
    mesh = gt_scene / "gt" / "mesh.ply"
    mesh.write_bytes(mesh.read_bytes()[:300])
    assert main(["view", str(gt_scene), "--export", str(tmp_path / "view.html")]) == 1
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err and "gt/mesh.ply" in lines[0], err


def test_a_runs_damaged_exported_mesh_is_left_out_with_a_warning(tmp_path, caplog):
    pytest.importorskip("viser")
    import trimesh

    from tacsplat.apps import viewer

    trimesh.creation.icosphere(subdivisions=2).export(tmp_path / "mesh.ply")
    data = (tmp_path / "mesh.ply").read_bytes()
    (tmp_path / "mesh.ply").write_bytes(data[:300])
    server = types.SimpleNamespace(scene=None, gui=None)  # (anything drawn would fail on these)
    view = viewer.View()
    with caplog.at_level(logging.WARNING, logger=viewer.log.name):
        viewer._exported_mesh(server, view, types.SimpleNamespace(path=tmp_path))
    assert view.mesh_node is None and "exported mesh" not in view.controls
    assert str(tmp_path / "mesh.ply") in caplog.records[-1].getMessage()
