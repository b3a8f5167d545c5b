"""The bounding sphere of an object (tacsplat.sim.objects, by tacsplat.geometry.minimum_sphere): trimesh's method
where it is fast (the library and held-out meshes keep the spheres their captures had), Welzl's exact minimum sphere
on a big convex hull, where trimesh's falls back to a loop of minutes, and one sphere computed per mesh loaded."""

import logging

import numpy as np
import pytest
import trimesh
from scipy.optimize import linprog

from tacsplat import geometry
from tacsplat.geometry import TRIMESH_SPHERE_MAX_HULL_POINTS, welzl_sphere
from tacsplat.sim.objects import _BUILDERS, bounding_sphere, load_mesh_object, make_object

pytestmark = pytest.mark.timeout(120)


def _is_minimum(points, centre, radius) -> bool:
    """Whether the sphere encloses the points and is the smallest that does: its centre lies in the convex hull of
    the points on its surface (else moving towards them would shrink it)."""
    distance = np.linalg.norm(points - centre, axis=1)
    support = points[distance > radius * (1 - 1e-9)]
    a_eq, b_eq = np.vstack([support.T, np.ones(len(support))]), np.r_[centre, 1.0]
    in_hull = linprog(np.zeros(len(support)), A_eq=a_eq, b_eq=b_eq, bounds=(0, None)).status == 0
    return bool(distance.max() <= radius and in_hull)


def _big_hull(points: int = int(1.4 * TRIMESH_SPHERE_MAX_HULL_POINTS)) -> np.ndarray:
    """Points evenly on the unit sphere and two spikes along x at 1.2 (they hide 17 % of the sphere from the hull,
    which keeps more than :data:`TRIMESH_SPHERE_MAX_HULL_POINTS`): their minimum sphere is the spikes' diameter,
    centred on the origin, radius 1.2."""
    i = np.arange(points) + 0.5
    z, phi = 1 - 2 * i / points, np.pi * (1 + 5**0.5) * i
    ring = np.sqrt(1 - z**2)
    return np.vstack([np.stack([ring * np.cos(phi), ring * np.sin(phi), z], axis=1), [[1.2, 0, 0], [-1.2, 0, 0]]])


@pytest.mark.parametrize("name", ["toaster", "bell", "car"])
def test_welzl_gives_trimeshs_sphere_where_four_points_hold_it(name):
    vertices = np.asarray(_BUILDERS[name][0]().vertices)
    centre, radius = trimesh.nsphere.minimum_nsphere(vertices)
    c, r = welzl_sphere(vertices)
    assert abs(r - radius) <= 1e-9 * radius and np.linalg.norm(c - centre) <= 1e-9 * radius


def test_welzl_gives_the_minimum_sphere_where_trimesh_gives_a_larger_one():
    vertices = np.asarray(_BUILDERS["teapot"][0]().vertices)  # held by two points, spout and handle
    c, r = welzl_sphere(vertices)
    assert _is_minimum(vertices, c, r) and r < 0.99 * trimesh.nsphere.minimum_nsphere(vertices)[1]
    tetrahedron = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1.0]])
    c, r = welzl_sphere(np.vstack([tetrahedron, 0.3 * tetrahedron]))
    assert np.allclose(c, 0, atol=1e-12) and r == pytest.approx(np.sqrt(3), rel=1e-12)
    sphere = trimesh.creation.icosphere(subdivisions=4).vertices  # all on one sphere
    c, r = welzl_sphere(sphere)
    assert np.allclose(c, 0, atol=1e-9) and r == pytest.approx(1.0, rel=1e-9)
    cloud = np.random.default_rng(0).normal(size=(3000, 3)) * [1.0, 0.3, 2.0]
    assert _is_minimum(cloud, *welzl_sphere(cloud))


def test_a_big_hull_skips_trimeshs_slow_method_and_says_what_it_does(monkeypatch, caplog):
    def slow(points):
        raise AssertionError("trimesh's method on a big hull: minutes in its fallback loop")

    monkeypatch.setattr(trimesh.nsphere, "minimum_nsphere", slow)
    points = _big_hull()
    mesh = trimesh.Trimesh(points * 3.0 + [1.0, 2.0, 3.0], np.zeros((0, 3), dtype=np.int64), process=False)
    with caplog.at_level(logging.INFO, logger="tacsplat.geometry"):
        centre, radius = bounding_sphere(mesh)
    assert np.allclose(centre, [1.0, 2.0, 3.0], atol=1e-12) and radius == pytest.approx(3.6, rel=1e-12)
    hull = len(trimesh.convex.hull_points(points))
    assert hull > TRIMESH_SPHERE_MAX_HULL_POINTS and f"{hull} convex-hull points" in caplog.text


def test_small_meshes_keep_trimeshs_sphere_bit_for_bit():
    obj = make_object("teapot")
    centre, radius = trimesh.nsphere.minimum_nsphere(np.asarray(obj.mesh.vertices))
    assert bounding_sphere(obj.mesh)[1] == radius and np.array_equal(bounding_sphere(obj.mesh)[0], centre)


def test_a_big_mesh_loaded_gets_its_sphere_computed_once(tmp_path, monkeypatch):
    mesh = trimesh.convex.convex_hull(_big_hull() * 90.0 + [5.0, 0.0, -40.0])  # millimetres, off the origin
    mesh.export(tmp_path / "ball.ply")
    computed = []
    welzl = geometry.welzl_sphere
    monkeypatch.setattr(geometry, "welzl_sphere", lambda points: computed.append(len(points)) or welzl(points))
    obj = load_mesh_object(tmp_path / "ball.ply", radius=0.08)
    assert obj.bounding_radius == pytest.approx(0.08, rel=1e-12)
    centre, radius = bounding_sphere(obj.mesh)
    assert np.allclose(centre, 0, atol=1e-12) and len(computed) == 1
    # the sphere moved and scaled with the mesh is the normalised mesh's own
    assert _is_minimum(np.asarray(obj.mesh.vertices), centre, radius * (1 + 1e-12))
