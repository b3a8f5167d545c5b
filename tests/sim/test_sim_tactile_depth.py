"""Tactile depth maps against analytic surfaces (tacsplat.sim.tactile.TactileDepthRenderer)."""

import numpy as np
import pytest
import trimesh

from tacsplat.errors import ConfigError, InvalidInputError
from tacsplat.geometry import look_at, make_pose, tactile_depth_to_points, tactile_pixel_grid
from tacsplat.sim.tactile import TactileConfig, TactileDepthRenderer

CFG = TactileConfig()


def tilted_sensor_pose(origin):
    """A sensor frame at ``origin`` with an arbitrary rotation (z is its gel normal)."""
    R = trimesh.transformations.rotation_matrix(0.7, [0.3, -0.5, 0.8])[:3, :3]
    return make_pose(R, origin)


def test_plane_pressed_one_millimetre_gives_a_flat_map():
    T = tilted_sensor_pose([0.02, -0.01, 0.3])
    # a large box whose face lies 1 mm behind the gel surface, facing the gel
    box = trimesh.creation.box([0.2, 0.2, 0.1])
    box.apply_translation([0, 0, 0.05 - 0.001])  # face at sensor z = -1 mm, body in front of the gel
    box.apply_transform(T)
    depth = TactileDepthRenderer(box, CFG).render(T)
    assert depth.shape == (CFG.height_px, CFG.width_px) and depth.dtype == np.float32
    assert np.abs(depth - 0.001).max() < 1e-7
    # lifting puts every point on the plane
    pts = tactile_depth_to_points(depth, CFG.pixel_size_m, T)
    assert len(pts) == depth.size
    assert np.abs((pts - T[:3, 3]) @ T[:3, 2] + 0.001).max() < 1e-7


@pytest.mark.parametrize("radius,press", [(0.01, 0.0008), (0.03, 0.0015), (0.005, 0.0005)])
def test_sphere_gives_the_analytic_cap_within_one_pixel(radius, press):
    T = tilted_sensor_pose([-0.1, 0.05, 0.2])
    centre_s = np.array([0.0011, -0.0007, radius - press])  # lowest point 'press' behind the gel surface
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=radius)
    sphere.apply_translation(centre_s)
    sphere.apply_transform(T)
    depth = TactileDepthRenderer(sphere, CFG).render(T).astype(np.float64)
    x, y = tactile_pixel_grid(CFG.height_px, CFG.width_px, CFG.pixel_size_m)
    rho2 = (x - centre_s[0]) ** 2 + (y - centre_s[1]) ** 2
    inside = rho2 < radius**2
    analytic = np.where(inside, np.clip(-(centre_s[2] - np.sqrt(np.where(inside, radius**2 - rho2, 0))), 0, None), 0)
    # one pixel's error: the change of the analytic depth across one pixel, plus the
    # icosphere's facet sagitta (r * (1 - cos(edge / 2r)), edge ~ 1.05 r / 2^6)
    slope = np.sqrt(rho2) / np.sqrt(np.maximum(radius**2 - rho2, 1e-12))
    sagitta = radius * (1 - np.cos(1.05 / 2**6 / 2))
    tol = np.where(analytic > 0, np.minimum(slope, 10) * CFG.pixel_size_m, CFG.pixel_size_m) + sagitta
    contact = analytic > 0
    assert np.all(np.abs(depth - analytic)[contact] <= tol[contact])
    half_diagonal = CFG.pixel_size_m / np.sqrt(2)  # the apex lies within this of a pixel centre
    assert depth.max() == pytest.approx(press, abs=sagitta + half_diagonal**2 / (2 * radius) + 1e-8)
    # the contact area matches the cap's footprint to within a ring of pixels
    footprint = np.pi * (2 * radius * press - press**2)
    ring = 2 * np.pi * np.sqrt(2 * radius * press) * CFG.pixel_size_m
    assert abs((depth > 0).sum() * CFG.pixel_size_m**2 - footprint) < ring


def test_no_contact_and_clamping():
    T = look_at([0, 0, 0.5], [0, 0, 0])  # sensor z points down at the origin
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.02)
    renderer = TactileDepthRenderer(sphere, CFG)
    assert not renderer.render(T).any()  # far away
    T_close = look_at([0, 0, 0.0205], [0, 0, 0])  # gel surface 0.5 mm outside: no contact
    assert not renderer.render(T_close).any()
    T_deep = look_at([0, 0, 0.016], [0, 0, 0])  # 4 mm into the sphere: clamped to the gel
    d = renderer.render(T_deep)
    assert d.max() == pytest.approx(CFG.gel_thickness_m) and (d > 0).any()
    T_inside = look_at([0, 0, 0.0], [0, 0, -1])  # the whole pad buried in the object
    assert np.all(renderer.render(T_inside) == pytest.approx(CFG.gel_thickness_m))


def test_bad_settings_and_poses():
    with pytest.raises(ConfigError, match="pixel_size_m"):
        TactileConfig(pixel_size_m=0)
    renderer = TactileDepthRenderer(trimesh.creation.icosphere(), CFG)
    with pytest.raises(InvalidInputError, match="T_world_sensor"):
        renderer.render(np.full((4, 4), np.nan))
