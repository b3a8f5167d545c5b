"""Initialisation: pycolmap triangulation with known poses, touch Gaussians, random fallback."""

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tacsplat.datasets import Scene
from tacsplat.errors import SceneFormatError
from tacsplat.geometry import invert_pose, look_at
from tacsplat.reconstruction.config import TrainConfig
from tacsplat.reconstruction.initialization import (
    InitConfig,
    foreground_mask,
    initial_gaussians,
    neighbour_scales,
    random_points,
    sfm_points,
    silhouette_hull_points,
    thin_touch_points,
    view_colors,
)
from tacsplat.reconstruction.trainer import Trainer, scene_scale

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import CAMERA_DISTANCE, RADIUS, backdrop_gradient, build_sphere_scene  # noqa: E402

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
    texture = cv2.resize(
        (rng.uniform(0, 1, (48, 48, 3)) * 255).astype(np.uint8), (480, 480), interpolation=cv2.INTER_CUBIC
    )
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


def _sphere_silhouettes(radius: float, directions, size: int = 96):
    """Exact silhouettes of a sphere at the origin seen from ``directions`` at 0.3 m."""
    Kc = np.array([[150.0, 0, size / 2], [0, 150.0, size / 2], [0, 0, 1]])
    silhouettes, poses = [], []
    v, u = np.mgrid[0:size, 0:size] + 0.5
    for d in directions:
        T_world_cam = look_at(0.3 * np.asarray(d, float) / np.linalg.norm(d), [0, 0, 0])
        rays = np.stack([(u - Kc[0, 2]) / Kc[0, 0], (v - Kc[1, 2]) / Kc[1, 1], np.ones_like(u)], -1)
        rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
        centre = invert_pose(T_world_cam)[:3, 3]  # the sphere centre in the camera frame
        along = rays @ centre
        miss = np.linalg.norm(rays * along[..., None] - centre, axis=-1)
        silhouettes.append(miss < radius)
        poses.append(T_world_cam)
    return silhouettes, [Kc] * len(directions), poses


def test_visual_hull_points_lie_near_the_sphere_and_not_in_the_box():
    directions = [[1, 0, 0.3], [-1, 0.2, 0.3], [0, 1, 0.3], [0.2, -1, 0.3], [0, 0, 1], [0.5, 0.5, -1]]
    silhouettes, Ks, poses = _sphere_silhouettes(0.05, directions)
    points = silhouette_hull_points(
        silhouettes, Ks, poses, np.full(3, -0.1), np.full(3, 0.1), 3000, 48, np.random.default_rng(0)
    )
    radii = np.linalg.norm(points, axis=1)
    assert points.shape == (3000, 3)
    assert radii.min() > 0.05 - 0.006  # never carved inside the sphere (one voxel is 4 mm)
    assert np.median(radii) < 0.05 + 0.012  # six views: the hull hugs the sphere; the box corner is at 0.17


def test_visual_hull_of_silhouettes_that_see_nothing_is_empty():
    silhouettes, Ks, poses = _sphere_silhouettes(0.05, [[1, 0, 0], [0, 1, 0]])
    empty = [np.zeros_like(s) for s in silhouettes]
    points = silhouette_hull_points(
        empty, Ks, poses, np.full(3, -0.1), np.full(3, 0.1), 100, 16, np.random.default_rng(0)
    )
    assert points.shape == (0, 3)


def test_an_object_cut_by_the_frame_is_not_carved_outside_that_frame():
    silhouettes, Ks, poses = _sphere_silhouettes(0.05, [[1, 0, 0], [0, 1, 0]])
    cut = silhouettes[0].copy()
    cut[:, :5] = True  # the object goes on past the left edge of view 0
    kept = silhouette_hull_points(
        [cut, silhouettes[1]], Ks, poses, np.full(3, -0.2), np.full(3, 0.2), 2000, 32, np.random.default_rng(0)
    )
    whole = silhouette_hull_points(
        silhouettes, Ks, poses, np.full(3, -0.2), np.full(3, 0.2), 2000, 32, np.random.default_rng(0)
    )
    assert np.abs(kept).max() > 0.12  # view 0 no longer bounds the hull outside its frame
    assert np.abs(whole).max() < 0.1


def test_foreground_keeps_backdrop_colored_reflections_inside_the_object():
    backdrop = np.ones((20, 20), bool)
    backdrop[5:15, 5:15] = False  # the object
    backdrop[8:11, 8:11] = True  # a highlight that mirrors the backdrop colour
    fg = foreground_mask(backdrop)
    assert fg[5:15, 5:15].all() and fg.sum() == 100
    assert not foreground_mask(np.ones((6, 6), bool)).any()


def test_view_colors_are_the_median_pixel_on_the_object_and_nan_off_it():
    # four views of a plane whose left half (x < 0) is red and right half blue; views 0 and 3 are all green
    texture = np.zeros((400, 400, 3), np.uint8)
    texture[:, :200] = (255, 0, 0)
    texture[:, 200:] = (0, 0, 255)
    images, Ks, poses = _plane_views(texture)
    images = [im.astype(np.float64) / 255.0 for im in images]
    images[0][:] = images[3][:] = (0.0, 1.0, 0.0)
    points = np.array([[-0.05, 0.02, 0.0], [0.05, -0.03, 0.0], [0.0, 0.0, 5.0]])  # the last behind every camera
    silhouettes = [np.ones((200, 200), bool)] * 3 + [np.zeros((200, 200), bool)]  # view 3 sees no object
    colors = view_colors(points, images, Ks, poses, silhouettes)
    assert colors.shape == (3, 3)
    np.testing.assert_allclose(colors[0], [1.0, 0.0, 0.0], atol=0.02)  # median of green, red, red: view 3 is out
    np.testing.assert_allclose(colors[1], [0.0, 0.0, 1.0], atol=0.02)
    assert np.isnan(colors[2]).all()
    no_silhouettes = view_colors(points, images, Ks, poses, [None] * 4)
    np.testing.assert_allclose(no_silhouettes[0], [0.5, 0.5, 0.0], atol=0.02)  # green, red, red, green


def test_one_training_view_scales_the_scene_by_its_distance_to_the_object(tmp_path):
    """Kerbl et al.'s extent (1.1 x the cameras' spread) of one camera is nil: its distance to the scene's centre
    stands in; more cameras keep theirs."""
    scene = Scene.load(build_sphere_scene(tmp_path / "sphere", size=16, train_views=3, test_views=1, touches=False))
    train = scene.split("train")
    centres = np.array([f.T_world_cam[:3, 3] for f in train])
    spread = np.linalg.norm(centres - centres.mean(axis=0), axis=1).max()
    assert scene_scale(train, scene.bounds()) == 1.1 * spread
    one = Trainer(scene, tmp_path / "run", TrainConfig(train_views=1, backend="cpu")).scene_scale
    assert one == pytest.approx(1.1 * CAMERA_DISTANCE, rel=0.1)


def test_a_scene_whose_cameras_are_nearer_than_the_near_plane_is_refused_at_initialisation(tmp_path):
    """Cameras a few millimetres from the object (a scene in the wrong unit): every Gaussian lies in front of the
    renderer's near plane and no view would show anything; one error says so rather than training on nothing."""
    path = build_sphere_scene(tmp_path / "sphere", size=16, train_views=3, test_views=1, touches=False)
    index = json.loads((path / "transforms.json").read_text())
    for frame in index["frames"]:  # the cameras 100 times nearer: 2.5 mm from the centre
        for row in frame["transform_matrix"][:3]:
            row[3] *= 0.01
    (path / "transforms.json").write_text(json.dumps(index))
    config = TrainConfig(backend="cpu", sh_degree=0, init=InitConfig(use_sfm=False, num_random_points=200))
    trainer = Trainer(Scene.load(path), tmp_path / "run", config)
    with pytest.raises(SceneFormatError, match="near plane"):
        trainer.initialize()


def test_training_views_whose_object_crosses_the_border_keep_their_backdrop_and_silhouette(tmp_path, caplog):
    """Close views (the sphere across the top edge of each) in front of a gradient: each view's backdrop is fitted
    (the gradient, not black), and its silhouette (the sphere's) is in the visual hull; a cluttered view has no
    backdrop, and a warning names its image."""
    path = build_sphere_scene(
        tmp_path / "sphere", size=32, train_views=4, test_views=1, touches=False, backdrop=True, centre_row=0.15
    )
    scene = Scene.load(path)
    config = TrainConfig(
        backend="cpu", use_touch=False, sh_degree=0, init=InitConfig(use_sfm=False, num_random_points=500)
    )
    trainer = Trainer(scene, tmp_path / "run", config)
    for frame, background, silhouette in zip(trainer.train_frames, trainer.backgrounds, trainer.silhouettes):
        sphere = scene.gt_depth(frame) > 0
        assert sphere[0].any()  # (the sphere crosses the top edge)
        np.testing.assert_allclose(background.numpy(), backdrop_gradient(32), atol=0.01)
        near = cv2.dilate(sphere.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # (the Gaussians' tails)
        assert silhouette is not None and silhouette[sphere].all() and not silhouette[~near].any()
    with caplog.at_level("INFO", logger="tacsplat.reconstruction.trainer"):
        trainer.initialize()
    assert "on the visual hull of 4 silhouettes" in caplog.text
    assert not [r for r in caplog.records if r.levelname == "WARNING"]

    cluttered = scene.split("train")[2].file_path
    cv2.imwrite(str(path / cluttered), np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8))
    caplog.clear()
    trainer = Trainer(Scene.load(path), tmp_path / "cluttered", config)
    with caplog.at_level("INFO", logger="tacsplat.reconstruction.trainer"):
        trainer.initialize()
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "training images whose border is not a smooth backdrop" in warnings[0]
    assert str(path / cluttered) in warnings[0]
    assert "on the visual hull of 3 silhouettes" in caplog.text


def test_a_blank_training_view_is_left_out_of_the_visual_hull_with_a_warning_naming_its_image(tmp_path, caplog):
    """One training image of uniform grey (a lens cap, a dropped frame) is all backdrop: its empty silhouette
    would carve the whole hull away. The other views' hull is used, and a warning names the image."""
    path = build_sphere_scene(tmp_path / "sphere", size=32, train_views=4, test_views=1, touches=False)
    scene = Scene.load(path)
    blank = scene.split("train")[1].file_path
    cv2.imwrite(str(path / blank), np.full((32, 32, 3), 128, np.uint8))
    config = TrainConfig(
        backend="cpu", use_touch=False, sh_degree=0, init=InitConfig(use_sfm=False, num_random_points=500)
    )
    trainer = Trainer(Scene.load(path), tmp_path / "run", config)
    with caplog.at_level("INFO", logger="tacsplat.reconstruction.trainer"):
        trainer.initialize()
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and str(path / blank) in warnings[0] and "shows no object" in warnings[0]
    assert "on the visual hull of 3 silhouettes" in caplog.text
    radii = np.linalg.norm(trainer.gaussians.means.detach().numpy(), axis=1)
    assert np.median(radii) < 2 * RADIUS  # on the hull around the sphere, not throughout the scene's bounds
