"""The sim-capture command (through the acquisition logger) and simulate-touches (tacsplat.sim.capture)."""



import numpy as np  # noqa: E402
import pytest  # noqa: E402
import trimesh  # noqa: E402

from tacsplat.cli import main  # noqa: E402
from tacsplat.datasets import Scene, SceneMeta, SceneWriter  # noqa: E402
from tacsplat.errors import ConfigError  # noqa: E402
from tacsplat.sim.capture import simulate_touches  # noqa: E402

CAPTURE_ARGS = ["sim-capture", "--object", "car", "--views", "2", "--test-views", "3", "--grasps", "2",
                "--resolution", "64", "--seed", "5"]


def _touch_signature(scene: Scene):
    return [(t.grasp, t.finger, t.T_world_sensor.round(9).tolist(), scene.load_touch_depth(t).tobytes()) for t in scene.touches]


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    out = tmp_path_factory.mktemp("cap") / "scene"
    assert main(CAPTURE_ARGS + ["--out", str(out)]) == 0
    return out


def test_sim_capture_writes_a_valid_scene_with_ground_truth(captured):
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


def test_resume_of_a_finished_capture_changes_nothing(captured, tmp_path):
    before = _touch_signature(Scene.load(captured))
    assert main(CAPTURE_ARGS + ["--out", str(captured), "--resume"]) == 0
    after = Scene.load(captured)
    assert len(after.frames) == 5 and _touch_signature(after) == before


def test_simulate_touches_on_an_imported_unit_scale_scene(captured, tmp_path):
    """Touches of a unit-scale mesh placed off-centre come back in the scene's frame and units."""
    source = Scene.load(captured)
    scale, offset = 1.0 / 0.08, np.array([0.5, -0.2, 0.1])
    mesh = trimesh.creation.capsule(height=1.0, radius=0.5, count=[48, 48])  # convex: no decomposition to wait for
    mesh.apply_scale(scale * 0.08 / mesh.bounding_sphere.primitive.radius)
    mesh.apply_translation(offset)
    mesh_path = tmp_path / "object.ply"
    mesh.export(mesh_path)
    imported = tmp_path / "imported"
    with SceneWriter.create(imported, source.intrinsics, SceneMeta(source="import", object="car")) as writer:
        for frame in source.frames[:2]:
            T = frame.T_world_cam.copy()
            T[:3, 3] = T[:3, 3] * scale + offset
            writer.add_frame(np.rint(source.load_image(frame) * 255).astype(np.uint8), T, frame.split)
    with pytest.raises(ConfigError, match="--out"):
        simulate_touches(mesh_path, imported, grasps=1)
    out = simulate_touches(mesh_path, imported, grasps=1, out=tmp_path / "touched", seed=2)
    scene = Scene.load(out)
    assert len(scene.frames) == 2 and len(scene.touches) == 4
    assert scene.sensor.pixel_size_m == pytest.approx(1.5e-4 * scale)
    points = scene.touch_points()
    _, distance, _ = trimesh.proximity.closest_point(mesh, points)
    assert len(points) > 0 and distance.mean() < 3e-4 * scale and distance.max() < 1e-3 * scale
    # a scene with this sensor model is extended in place, numbering grasps on
    simulate_touches(mesh_path, out, grasps=1, seed=3)
    extended = Scene.load(out)
    assert len(extended.touches) == 8 and sorted({t.grasp for t in extended.touches}) == [0, 1]
    with pytest.raises(ConfigError, match="in place"):
        simulate_touches(mesh_path, out, grasps=1, out=tmp_path / "other")
