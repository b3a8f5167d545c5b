"""Initialisation: pycolmap triangulation with known poses, touch Gaussians, random fallback."""

import cv2
import numpy as np
import pytest

from tacsplat.geometry import invert_pose, look_at
from tacsplat.reconstruction.initialization import (
    InitConfig,
    initial_gaussians,
    neighbour_scales,
    random_points,
    sfm_points,
    thin_touch_points,
)

K = np.array([[200.0, 0, 100], [0, 200.0, 100], [0, 0, 1]])


def _plane_views(texture: np.ndarray, count: int = 4):
    """Views of the textured square [-0.1, 0.1]^2 on the plane z = 0, rendered by homography."""
    size = texture.shape[0]
    tex_to_world = np.array([[0.2 / size, 0, -0.1], [0, 0.2 / size, -0.1], [0, 0, 1]])
    images, poses = [], []
    for a in np.linspace(0.0, 1.0, count):
        T_world_cam = look_at([0.25 * np.cos(a), 0.25 * np.sin(a), 0.3], [0, 0, 0])
        T_cam_world = invert_pose(T_world_cam)
        H = K @ T_cam_world[:3, [0, 1, 3]] @ tex_to_world
        images.append(cv2.warpPerspective(texture, H, (200, 200)))
        poses.append(T_world_cam)
    return images, [K] * count, poses


def test_sfm_with_known_poses_triangulates_points_on_the_textured_plane():
    rng = np.random.default_rng(0)
    texture = cv2.resize((rng.uniform(0, 1, (48, 48, 3)) * 255).astype(np.uint8), (480, 480),
                         interpolation=cv2.INTER_CUBIC)
    result = sfm_points(*_plane_views(texture))
    assert len(result.points) > 50
    assert np.median(np.abs(result.points[:, 2])) < 0.002  # on z = 0 (metres), in the known world frame
    assert np.all(np.abs(result.points[:, :2]).max(axis=1) < 0.12)
    assert result.colors.shape == result.points.shape and (result.colors >= 0).all() and (result.colors <= 1).all()


def test_sfm_on_featureless_glossy_like_views_returns_no_points_without_crashing():
    flat = np.full((480, 480, 3), 200, np.uint8)
    result = sfm_points(*_plane_views(flat, count=3))
    assert result.points.shape == (0, 3)


def test_touch_points_are_thinned_per_voxel_and_capped():
    rng = np.random.default_rng(0)
    dense = rng.uniform(0, 0.01, size=(20000, 3))  # a 1 cm cube, 1000 voxels of 1 mm
    thinned = thin_touch_points(dense, InitConfig(touch_voxel_size=0.001, max_touch_points=5000), rng)
    assert len(thinned) == len(np.unique(np.floor(dense / 0.001).astype(int), axis=0))
    capped = thin_touch_points(dense, InitConfig(touch_voxel_size=0.001, max_touch_points=100), rng)
    assert len(capped) == 100


def test_initial_gaussians_mark_touch_points_and_take_scales_from_neighbours():
    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(np.arange(4) * 0.01, np.arange(4) * 0.01, [0.0], indexing="ij"), -1).reshape(-1, 3)
    np.testing.assert_allclose(neighbour_scales(grid)[5], 0.01)  # an inner grid point: 3 neighbours at 1 cm
    points, colors = random_points(np.zeros(3), np.ones(3), 10, rng)
    assert points.min() >= 0 and points.max() <= 1
    g = initial_gaussians(points, colors, grid, sh_degree=2, config=InitConfig(initial_opacity=0.1), rng=rng)
    assert len(g) == 26 and g.num_touch == 16
    assert g.from_touch[10:].all() and not g.from_touch[:10].any()
    assert g.opacities.detach().numpy() == pytest.approx(0.1)
    assert tuple(g.params["shN"].shape) == (26, 8, 3)
