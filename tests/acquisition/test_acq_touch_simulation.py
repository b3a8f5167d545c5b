"""simulate-touches (tacsplat.acquisition.touch_simulation): it taps exactly as sim-capture does (the one grasp
controller), maps touches of a unit-scale scene back into its frame and units, and never drops a touch it finds."""

import numpy as np
import pytest
import trimesh

from tacsplat.acquisition import touch_simulation
from tacsplat.acquisition.sim_capture import sim_capture, sim_rig_config
from tacsplat.acquisition.touch_simulation import simulate_touches
from tacsplat.cli import main
from tacsplat.datasets import Scene, SceneMeta, SceneWriter, copy_scene
from tacsplat.errors import ConfigError, UsageError

pytestmark = pytest.mark.timeout(180)

RADIUS = 0.08


def _capsule(radius: float, offset=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    """A convex mesh (no convex decomposition to wait for) of bounding radius ``radius``."""
    mesh = trimesh.creation.capsule(height=1.0, radius=0.5, count=[48, 48])
    mesh.apply_scale(radius / mesh.bounding_sphere.primitive.radius)
    mesh.apply_translation(offset)
    return mesh


@pytest.fixture(scope="module")
def capsule(tmp_path_factory):
    """A capsule mesh in metres at the origin, and its sim-capture (2 views, 2 grasps, seed 4)."""
    root = tmp_path_factory.mktemp("capsule")
    mesh = root / "capsule.ply"
    _capsule(RADIUS).export(mesh)
    config = sim_rig_config(
        mesh=str(mesh), object_radius=RADIUS, views=2, test_views=0, grasps=2, resolution=64, seed=4
    )
    sim_capture(config, root / "scene", progress=False)
    return mesh, root / "scene"


def test_simulate_touches_taps_exactly_as_sim_capture(capsule, tmp_path):
    mesh, captured = capsule
    scene = Scene.load(captured)
    bare = copy_scene(scene, tmp_path / "bare", touches=[])  # the same views, the same sensor model, no touches
    simulate_touches(mesh, bare, grasps=2, object_radius=RADIUS, seed=4)
    simulated = Scene.load(bare)
    assert [(t.grasp, t.finger) for t in simulated.touches] == [(t.grasp, t.finger) for t in scene.touches]
    assert sum(t.in_contact for t in scene.touches) >= 2
    for new, old in zip(simulated.touches, scene.touches):
        assert np.allclose(new.T_world_sensor, old.T_world_sensor, atol=1e-9)
        assert np.allclose(simulated.load_touch_depth(new), scene.load_touch_depth(old), atol=1e-9)


def test_touches_of_an_imported_unit_scale_scene_come_back_in_its_frame_and_units(capsule, tmp_path, capsys):
    _, captured = capsule
    source = Scene.load(captured)
    scale, offset = 1.0 / RADIUS, np.array([0.5, -0.2, 0.1])  # the capsule at radius 1, off-centre
    mesh = _capsule(RADIUS * scale, offset)
    mesh_path = tmp_path / "object.ply"
    mesh.export(mesh_path)
    imported = tmp_path / "imported"
    with SceneWriter.create(imported, source.intrinsics, SceneMeta(source="import", object="capsule")) as writer:
        for frame in source.frames:
            T = frame.T_world_cam.copy()
            T[:3, 3] = T[:3, 3] * scale + offset
            writer.add_frame(np.rint(source.load_image(frame) * 255).astype(np.uint8), T, frame.split)
    with pytest.raises(ConfigError, match="--out"):
        simulate_touches(mesh_path, imported, grasps=1)
    out = tmp_path / "touched"
    assert (
        main(
            [
                "simulate-touches",
                "--mesh",
                str(mesh_path),
                str(imported),
                "--grasps",
                "1",
                "--out",
                str(out),
                "--seed",
                "2",
            ]
        )
        == 0
    )
    assert f"touches written to {out}" in capsys.readouterr().out
    scene = Scene.load(out)
    assert len(scene.frames) == 2 and len(scene.touches) == 4
    assert scene.meta.capture_plan["simulated_touches"] == {
        "mesh": str(mesh_path),
        "grasps": 1,
        "seed": 2,
        "touches": {"model": "gel"},
    }
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


def test_extending_a_scene_keeps_a_grasp_with_fewer_touches_than_pads(capsule, tmp_path):
    mesh, captured = capsule
    scene = Scene.load(captured)
    kept = scene.touches[:6]  # grasp 0 whole, two touches of grasp 1 (as a subsampling bench leaves them)
    partial = copy_scene(scene, tmp_path / "partial", touches=kept)
    simulate_touches(mesh, partial, grasps=1, object_radius=RADIUS, seed=4)
    extended = Scene.load(partial)
    assert [(t.grasp, t.finger) for t in extended.touches[:6]] == [(t.grasp, t.finger) for t in kept]
    assert [t.grasp for t in extended.touches[6:]] == [2] * 4


def test_a_mesh_of_other_units_than_the_scene_is_refused_before_the_twin_starts(capsule, tmp_path, monkeypatch, capsys):
    _, captured = capsule  # a scene in metres

    def no_twin(*args, **kwargs):
        raise AssertionError("the twin (and CoACD) started before the mesh's size was compared with the scene's")

    monkeypatch.setattr(touch_simulation, "SimTwin", no_twin)
    in_mm = tmp_path / "capsule_mm.ply"
    _capsule(RADIUS * 1000).export(in_mm)
    assert main(["simulate-touches", str(captured), "--grasps", "1", "--mesh", str(in_mm)]) == 2  # a usage error
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--mesh" in err and "--object-radius" not in err
    assert "bounding radius is 80 in its file's units" in err and "~0.08" in err and "in millimetres" in err
    larger = tmp_path / "capsule_larger.ply"  # in metres, but not the scene's size at --object-radius 0.08
    _capsule(0.1).export(larger)
    with pytest.raises(UsageError, match=r"^--object-radius: .*at --object-radius 0\.1 \(m\), not 0\.08 m"):
        simulate_touches(larger, captured, grasps=1)
