"""Usage mistakes of simulate-touches exit 2, as every command's usage errors do (the README,
docs/what-happens-when.md): one line naming the option, its text as before, and nothing written (calibrate mounts
without --hand-eye on a rig naming no hand-eye file: test_acq_calibration_chain_guards.py)."""

import numpy as np
import pytest
import trimesh

from tacsplat.cli import main
from tacsplat.datasets import SceneMeta, SceneWriter, copy_scene
from tacsplat.sim.twin import TwinConfig, pad_sensor_model
from tacsplat.types import CameraIntrinsics

pytestmark = pytest.mark.timeout(120)


def _one_usage_line(capsys, command: str, text: str) -> None:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines == [f"tacsplat {command}: error: {text} (see tacsplat {command} --help)"], err


def _files(folder) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def imported(tmp_path):
    """(an imported scene: no tactile sensor model, its copy with the pads' model, a mesh)."""
    scene = tmp_path / "imported"
    K = CameraIntrinsics(np.array([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]]), 16, 16)
    T = np.eye(4)
    T[2, 3] = -1.0
    with SceneWriter.create(scene, K, SceneMeta(source="import", object="sphere")) as writer:
        writer.add_frame(np.zeros((16, 16, 3), np.uint8), T, "train")
    sensed = copy_scene(scene, tmp_path / "sensed", sensor=pad_sensor_model(TwinConfig().tactile))
    mesh = tmp_path / "sphere.ply"
    trimesh.creation.icosphere(radius=0.08).export(mesh)
    return scene, sensed, mesh


def test_simulate_touches_into_an_import_without_out_or_into_a_sensed_scene_with_out_is_a_usage_error(
    imported, tmp_path, capsys
):
    scene, sensed, mesh = imported
    before = {scene: _files(scene), sensed: _files(sensed)}
    assert main(["simulate-touches", str(scene), "--mesh", str(mesh), "--grasps", "2"]) == 2
    text = f"--out: {scene} has no tactile sensor model (an import): pass --out NEW_SCENE"
    _one_usage_line(capsys, "simulate-touches", text)
    assert main(["simulate-touches", str(sensed), "--mesh", str(mesh), "--out", str(tmp_path / "new")]) == 2
    text = f"--out: {sensed} already holds touches; it is extended in place, drop --out"
    _one_usage_line(capsys, "simulate-touches", text)
    assert {folder: _files(folder) for folder in before} == before and not (tmp_path / "new").exists()


def test_simulate_touches_on_a_scene_without_a_mesh_and_no_mesh_option_is_a_usage_error(imported, tmp_path, capsys):
    scene, _, _ = imported
    before = _files(scene)
    assert main(["simulate-touches", str(scene), "--out", str(tmp_path / "new"), "--grasps", "2"]) == 2
    _one_usage_line(capsys, "simulate-touches", f"--mesh: {scene} has no ground-truth mesh or points: pass --mesh")
    assert _files(scene) == before and not (tmp_path / "new").exists()
