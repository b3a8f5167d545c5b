"""Simulated capture through the same logger as the real rig: touches on the object's surface, the operator
session and the unattended job write the same scene, a grasp cut short is redone identically, and the
`tacsplat sim-capture` command writes a valid scene that a resume leaves as it is."""

import io
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from tacsplat.acquisition.config import load_rig  # noqa: E402
from tacsplat.acquisition.operator_session import run_capture  # noqa: E402
from tacsplat.acquisition.sim_capture import sim_capture, sim_rig_config  # noqa: E402
from tacsplat.cli import main  # noqa: E402
from tacsplat.datasets import Scene, SceneWriter, check_scene  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from acq_helpers import ScriptedKeys  # noqa: E402

pytestmark = pytest.mark.timeout(180)

PLAN = dict(object="bell", views=2, test_views=1, grasps=2, resolution=64, seed=3)


def _records(path: Path) -> list:
    scene = Scene.load(path)
    frames = [((path / f.file_path).read_bytes(), f.split, f.T_world_cam.tobytes()) for f in scene.frames]
    touches = [
        (scene.load_touch_depth(t).tobytes(), t.grasp, t.finger, t.T_world_sensor.tobytes()) for t in scene.touches
    ]
    return frames + touches


@pytest.fixture(scope="module")
def sim_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "scene"
    timings = sim_capture(sim_rig_config(**PLAN), out, progress=False)
    assert set(timings) == {"setup_s", "views_s", "grasps_s", "total_s"}
    return out


def test_sim_capture_scene_is_valid_and_every_touch_lies_on_the_object(sim_scene):
    scene, problems = check_scene(sim_scene)
    assert problems == []
    assert [f.split for f in scene.frames] == ["train", "train", "test"]
    assert scene.gt_depth(scene.frames[0]) is None and scene.gt_depth(scene.frames[2]) is not None
    assert scene.meta.source == "sim" and scene.meta.object == "bell"
    assert sorted({t.grasp for t in scene.touches}) == [0, 1]
    for g in (0, 1):  # four touches a grasp, at least one in contact (no-contact pads recorded as such)
        touches = [t for t in scene.touches if t.grasp == g]
        assert [t.finger for t in touches] == ["index", "middle", "ring", "thumb"]
        assert any(t.in_contact for t in touches)
    mesh = trimesh.load(scene.gt_mesh_path, force="mesh")
    points = scene.touch_points()
    distance = np.abs(trimesh.proximity.signed_distance(mesh, points))
    assert len(points) > 50
    assert distance.mean() < 3e-4 and distance.max() < 1e-3, (distance.mean(), distance.max())


def test_operator_session_on_the_twin_writes_the_same_scene_as_the_unattended_job(sim_scene, tmp_path):
    rig = tmp_path / "sim.yaml"
    rig.write_text(
        yaml.safe_dump(
            {
                "rig": "sim",
                "object": "bell",
                "sim": {"object": "bell", "resolution": 64, "seed": 3},
                "plan": {
                    "views": {"train": 2, "test": 1, "mode": "hemisphere"},
                    "grasps": {"count": 2, "mode": "random", "seed": 3},
                },
            }
        )
    )
    output = io.StringIO()
    code = run_capture(load_rig(rig), tmp_path / "scene", keys=ScriptedKeys("\n\n\ngg"), output=output)
    assert code == 0, output.getvalue()
    assert "camera pose: ground truth" in output.getvalue()
    assert _records(tmp_path / "scene") == _records(sim_scene)


def test_sim_grasp_cut_short_is_redone_identically_on_resume(sim_scene, tmp_path):
    import shutil

    out = tmp_path / "scene"
    shutil.copytree(sim_scene, out)
    complete = _records(out)
    with SceneWriter.resume(out) as writer:  # what a kill after two of grasp 1's four touches leaves
        writer.remove_last()
        writer.remove_last()
    sim_capture(sim_rig_config(**PLAN), out, resume=True, progress=False)
    assert _records(out) == complete


CAPTURE_ARGS = [
    "sim-capture",
    "--object",
    "car",
    "--views",
    "2",
    "--test-views",
    "3",
    "--grasps",
    "2",
    "--resolution",
    "64",
    "--seed",
    "5",
]


def _touch_signature(scene: Scene):
    return [
        (t.grasp, t.finger, t.T_world_sensor.round(9).tolist(), scene.load_touch_depth(t).tobytes())
        for t in scene.touches
    ]


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    out = tmp_path_factory.mktemp("cap") / "scene"
    assert main(CAPTURE_ARGS + ["--out", str(out)]) == 0
    return out


def test_sim_capture_command_writes_a_valid_scene_with_ground_truth(captured):
    scene = Scene.load(captured)
    assert scene.meta.source == "sim" and scene.meta.object == "car"
    assert len(scene.split("train")) == 2 and len(scene.split("test")) == 3
    assert all(scene.gt_depth(f) is not None for f in scene.split("test"))
    assert len(scene.touches) == 8 and {t.finger for t in scene.touches} == {"index", "middle", "ring", "thumb"}
    mesh = trimesh.load(scene.gt_mesh_path, force="mesh")
    points = scene.touch_points()
    _, distance, _ = trimesh.proximity.closest_point(mesh, points)
    assert len(points) > 0 and distance.mean() < 3e-4 and distance.max() < 1e-3
    depth = scene.gt_depth(scene.split("test")[0])
    assert depth.shape == (64, 64) and (depth > 0).any()


def test_resume_of_a_finished_capture_changes_nothing(captured):
    before = _touch_signature(Scene.load(captured))
    assert main(CAPTURE_ARGS + ["--out", str(captured), "--resume"]) == 0
    after = Scene.load(captured)
    assert len(after.frames) == 5 and _touch_signature(after) == before


def test_a_mesh_capture_records_where_the_files_points_went(tmp_path):
    """--keep-size keeps the mesh's size, not its frame (the twin centres it on its bounding sphere): the scene's
    "mesh_frame" annotation maps the file's points onto its ground-truth mesh."""
    mesh = trimesh.creation.capsule(height=0.1, radius=0.04, count=[16, 16])  # convex: no CoACD to wait for
    mesh.apply_translation([0.3, -0.1, 0.05])
    path = tmp_path / "can.ply"
    mesh.export(path)
    out = tmp_path / "scene"
    args = ["--views", "1", "--test-views", "0", "--grasps", "0", "--resolution", "32"]
    assert main(["sim-capture", "--mesh", str(path), "--keep-size", "--out", str(out), *args]) == 0
    scene = Scene.load(out)
    frame = scene.annotations["mesh_frame"]
    assert frame["scale"] == 1.0 and np.linalg.norm(np.add(frame["translation_m"], [0.3, -0.1, 0.05])) < 1e-3
    placed = frame["scale"] * np.asarray(mesh.vertices) + frame["translation_m"]
    gt = trimesh.load(scene.gt_mesh_path, force="mesh", process=False)
    _, distance, _ = trimesh.proximity.closest_point(gt, placed)
    assert distance.max() < 1e-6
    assert main(["sim-capture", "--mesh", str(path), "--keep-size", "--out", str(out), *args, "--resume"]) == 0
    assert Scene.load(out).annotations == {"mesh_frame": frame}
