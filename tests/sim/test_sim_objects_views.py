"""The object library and the hemisphere views (tacsplat.sim.objects, tacsplat.sim.views)."""

import numpy as np
import pytest
import trimesh

from tacsplat.errors import ConfigError
from tacsplat.sim.objects import OBJECT_NAMES, bounding_sphere, load_mesh_object, make_object
from tacsplat.sim.views import ViewConfig, hemisphere_views


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_library_objects_are_watertight_and_graspable_sized(name):
    obj = make_object(name)
    assert obj.mesh.is_watertight and obj.mesh.is_winding_consistent and obj.mesh.volume > 0
    centre, radius = bounding_sphere(obj.mesh)
    assert radius == pytest.approx(0.08, rel=1e-6)
    assert np.linalg.norm(centre) < 1e-6
    assert obj.material.specular >= 0.8 and obj.material.shininess >= 0.8
    assert len(OBJECT_NAMES) >= 6


def test_object_radius_option_scales():
    assert make_object("torus", 0.05).bounding_radius == pytest.approx(0.05, rel=1e-6)


def test_user_mesh_is_scaled_unless_already_the_size(tmp_path):
    box = trimesh.creation.box([1.0, 2.0, 3.0])
    box.apply_translation([5, 5, 5])
    box.export(tmp_path / "box.stl")
    obj = load_mesh_object(tmp_path / "box.stl", radius=0.1)
    assert obj.bounding_radius == pytest.approx(0.1, rel=1e-6)
    assert obj.mesh.extents == pytest.approx(np.array([1, 2, 3]) * 0.1 / np.sqrt(14) * 2, rel=1e-6)
    sized = trimesh.creation.icosphere(radius=0.08 * (1 + 5e-4))  # within 0.1 % of the target size
    sized.export(tmp_path / "ball.ply")
    kept = load_mesh_object(tmp_path / "ball.ply")
    assert kept.mesh.extents == pytest.approx(sized.extents, rel=1e-7)
    assert kept.bounding_radius == pytest.approx(0.08 * (1 + 5e-4), rel=1e-7)


def test_bad_object_choices_are_named():
    with pytest.raises(ConfigError, match="object.*'vase'"):
        make_object("vase")
    with pytest.raises(ConfigError, match="mesh.*not found"):
        load_mesh_object("/nonexistent/thing.obj")
    with pytest.raises(ConfigError, match="object_radius"):
        make_object("torus", -1.0)


def test_hemisphere_views_look_at_the_object_from_above():
    train, test = hemisphere_views(5, 24, object_radius=0.08, seed=3)
    assert len(train) == 5 and len(test) == 24
    cfg = ViewConfig()
    for T in train + test:
        eye, forward = T[:3, 3], T[:3, 2]
        assert np.linalg.norm(eye) == pytest.approx(cfg.radius_factor * 0.08)
        assert forward == pytest.approx(-eye / np.linalg.norm(eye))  # optical axis through the centre
        elevation = np.degrees(np.arcsin(eye[2] / np.linalg.norm(eye)))
        assert cfg.min_elevation_deg - 1e-9 <= elevation <= cfg.max_elevation_deg + 1e-9
        assert T[:3, 1] @ [0, 0, 1] < 0  # image rows go down the world
    again, _ = hemisphere_views(5, 0, object_radius=0.08, seed=3)
    assert all(np.array_equal(a, b) for a, b in zip(train, again))
    other, _ = hemisphere_views(5, 0, object_radius=0.08, seed=4)
    assert not np.allclose(train[0], other[0])
    with pytest.raises(ConfigError):
        hemisphere_views(-1, 3, 0.08)


def test_bounding_sphere_follows_the_vertices_it_is_kept_for():
    """The kept spheres are keyed by the vertices: a mesh changed in place gets its new sphere, and changing a
    returned centre changes nothing kept."""
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    centre, radius = bounding_sphere(mesh)
    assert radius == pytest.approx(0.5, rel=1e-6) and np.allclose(centre, 0.0, atol=1e-9)
    centre += 7.0
    assert np.allclose(bounding_sphere(mesh)[0], 0.0, atol=1e-9)  # the same vertices: the kept sphere, unchanged
    mesh.apply_scale(2.0)
    mesh.apply_translation([0.1, 0.0, 0.0])
    centre, radius = bounding_sphere(mesh)
    assert radius == pytest.approx(1.0, rel=1e-6) and np.allclose(centre, [0.1, 0.0, 0.0], atol=1e-6)


def test_a_view_radius_whose_camera_clips_the_object_is_refused(tmp_path, monkeypatch):
    """MuJoCo clips what is nearer a camera than its near plane: a view radius just outside the object rendered
    its far inside, written as ground-truth depth. The nearest radius accepted sees the surface."""
    from tacsplat.acquisition.config import CapturePlan, GraspPlan, RigConfig, SimConfig, ViewPlan, validate
    from tacsplat.geometry import look_at
    from tacsplat.sim import VIEW_ZNEAR_M
    from tacsplat.sim.twin import SimTwin, TwinConfig

    monkeypatch.setenv("TACSPLAT_CACHE", str(tmp_path / "cache"))
    trimesh.creation.icosphere(subdivisions=3).export(tmp_path / "ball.obj")

    def config(radius_m):
        views = ViewPlan(train=1, test=1, mode="hemisphere", radius_m=radius_m)
        sim = SimConfig(mesh=str(tmp_path / "ball.obj"), object_radius=0.08)
        return RigConfig(rig="sim", sim=sim, plan=CapturePlan(views, GraspPlan(count=0, mode="random")))

    with pytest.raises(ConfigError) as err:
        validate(config(0.085))
    assert err.value.key == "plan.views.radius_m" and "near plane" in str(err.value)
    nearest = 0.08 + 2 * VIEW_ZNEAR_M
    validate(config(nearest))
    with SimTwin(TwinConfig(mesh_path=str(tmp_path / "ball.obj"), camera_width=33, camera_height=33)) as twin:
        twin.move_camera(look_at(np.array([nearest, 0.0, 0.0]), np.zeros(3)))
        assert twin.view_camera.read_depth()[16, 16] == pytest.approx(nearest - 0.08, abs=1e-3)
