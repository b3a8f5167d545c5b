"""Where the twin's hand goes for a grasp: approaches that stay outside the object, whatever its tessellation."""

import numpy as np
import pytest
import trimesh

from tacsplat.sim.grasps import sample_hand_pose
from tacsplat.sim.twin import SimTwin, TwinConfig

pytestmark = pytest.mark.timeout(300)


@pytest.fixture
def cad_cube(tmp_path, monkeypatch):
    """A CAD box: 8 vertices, 12 triangles (faces far larger than the hand's footprint at radius 0.3 m)."""
    monkeypatch.setenv("TACSPLAT_CACHE", str(tmp_path / "cache"))
    path = tmp_path / "cube.obj"
    trimesh.creation.box([1.0, 1.0, 1.0]).export(path)
    return path


def test_the_palm_stays_outside_a_low_poly_mesh(cad_cube):
    """The palm's height comes from the surface under the hand's footprint, not only from its vertices: on a box
    with no vertex under the footprint the palm used to be put inside the object."""
    with SimTwin(TwinConfig(mesh_path=str(cad_cube), object_radius=0.3, camera_width=16, camera_height=16)) as twin:
        rng = np.random.default_rng(0)
        palms = np.array([sample_hand_pose(twin, rng)[:3, 3] for _ in range(200)])
        inside = trimesh.proximity.signed_distance(twin.object_mesh, palms)  # > 0 inside
    assert inside.max() < 0, f"{int((inside >= 0).sum())} of 200 palm centres inside the box"


def test_touches_on_a_low_poly_mesh_lie_on_its_surface(cad_cube, tmp_path):
    from tacsplat.acquisition.sim_capture import sim_capture, sim_rig_config
    from tacsplat.datasets import Scene
    from tacsplat.geometry import tactile_depth_to_points

    config = sim_rig_config(
        mesh=str(cad_cube), object_radius=0.3, views=1, test_views=0, grasps=2, resolution=16, seed=1
    )
    sim_capture(config, tmp_path / "scene", progress=False)
    scene = Scene.load(tmp_path / "scene")
    mesh = trimesh.load(scene.gt_mesh_path, force="mesh")
    touched = [t for t in scene.touches if t.in_contact]
    assert touched
    for t in touched:
        points = tactile_depth_to_points(scene.load_touch_depth(t), scene.sensor.pixel_size_m, t.T_world_sensor)
        distance = np.abs(trimesh.proximity.signed_distance(mesh, points))
        assert distance.max() < 1e-3, f"grasp {t.grasp} {t.finger}: a contact point {distance.max():.4f} m off"


def test_an_approach_whose_palm_meets_the_hulls_is_drawn_again(cad_cube):
    """A palm that would sit inside the collision hulls is never returned: here every approach does (a palm gap
    reaching 5 cm into the object), and the sampler says so instead of placing the hand inside."""
    from tacsplat.errors import SimulationError
    from tacsplat.sim.grasps import MAX_APPROACH_DRAWS, GraspConfig

    with SimTwin(TwinConfig(mesh_path=str(cad_cube), object_radius=0.3, camera_width=16, camera_height=16)) as twin:
        with pytest.raises(SimulationError, match=f"{MAX_APPROACH_DRAWS} directions.*palm"):
            sample_hand_pose(twin, np.random.default_rng(0), GraspConfig(palm_gap_m=-0.05))
