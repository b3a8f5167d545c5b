"""Metrics on known inputs and the 3DGS PLY round trip."""

import math
import re

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from tacsplat.errors import InvalidInputError, SceneFormatError
from tacsplat.reconstruction.gaussians import Gaussians, num_sh_bases
from tacsplat.reconstruction.metrics import (
    ReferenceCloud,
    bounding_sphere_radius,
    chamfer_distance,
    chamfer_distance_parts,
    chamfer_terms_paper,
    depth_to_points,
    psnr,
    ssim,
    ssim_map,
)
from tacsplat.reconstruction.ply import load_ply, save_ply


def test_psnr_of_known_noise():
    target = torch.full((10, 12, 3), 0.5)
    signs = torch.where(torch.rand(10, 12, 3, generator=torch.Generator().manual_seed(1)) > 0.5, 1.0, -1.0)
    assert psnr(target + 0.1 * signs, target) == pytest.approx(20.0, abs=1e-4)  # MSE 0.01
    assert psnr(target, target) == math.inf


def test_ssim_of_identical_images_is_one_and_of_constants_matches_the_formula():
    image = torch.rand(20, 24, 3, generator=torch.Generator().manual_seed(2))
    assert ssim(image, image) == pytest.approx(1.0, abs=1e-12)
    a, b = torch.full((30, 30, 1), 0.2, dtype=torch.float64), torch.full((30, 30, 1), 0.6, dtype=torch.float64)
    c1 = 0.01**2
    centre = ssim_map(a, b)[0, 15, 15, 0].item()  # away from the zero padding
    assert centre == pytest.approx((2 * 0.2 * 0.6 + c1) / (0.2**2 + 0.6**2 + c1), rel=1e-9)
    assert ssim(image, 1 - image) < 0.5


def test_chamfer_distance_of_identical_clouds_is_zero_and_of_a_shift_is_shift_over_radius():
    grid = np.stack(np.meshgrid(*[np.arange(5) * 0.01] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    assert chamfer_distance(grid, grid, radius=0.05) == 0.0
    shifted = grid + np.array([0.001, 0.0, 0.0])  # smaller than half the 1 cm spacing
    assert chamfer_distance(shifted, grid, radius=0.05) == pytest.approx(0.001 / 0.05, rel=1e-9)
    assert chamfer_distance(np.zeros((0, 3)), grid) == math.inf
    with pytest.raises(InvalidInputError, match="NaN"):
        chamfer_distance(grid + np.nan, grid)


def test_chamfer_split_gives_each_part_its_own_error():
    grid = np.stack(np.meshgrid(*[np.arange(5) * 0.01] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    far = grid + np.array([1.0, 0.0, 0.0])  # a second part far from the first
    gt = np.concatenate([grid, far])
    part = np.arange(len(gt)) < len(grid)
    predicted = np.concatenate([grid, far + np.array([0.0, 0.002, 0.0])])  # only the second part is off
    _, exact, off = chamfer_distance_parts(predicted, gt, part, radius=0.05)
    assert exact == 0.0
    assert off == pytest.approx(0.002 / 0.05, rel=1e-9)
    # the parts add up to the whole CD when they hold equal numbers of points each way
    assert 0.5 * (exact + off) == pytest.approx(chamfer_distance(predicted, gt, radius=0.05), rel=1e-9)
    # nothing predicted near the second part: its accuracy term is 0, its completeness the distance to the first
    missing = chamfer_distance_parts(grid, gt, part, radius=0.05)[2]
    assert missing == pytest.approx(
        0.5 * float(np.linalg.norm(far[:, None] - grid[None], axis=-1).min(1).mean()) / 0.05
    )
    assert math.isnan(chamfer_distance_parts(predicted, gt, np.ones(len(gt), bool))[2])
    with pytest.raises(InvalidInputError, match="part has 3 entries"):
        chamfer_distance_parts(predicted, gt, np.ones(3, bool))


def test_a_reference_cloud_reused_gives_what_the_array_gives():
    rng = np.random.default_rng(3)
    gt = rng.normal(size=(500, 3))
    part = gt[:, 0] > 0
    reference = ReferenceCloud(gt, radius=2.0)
    for predicted in (gt + 0.01 * rng.normal(size=gt.shape), rng.normal(size=(80, 3))):  # the tree serves both
        assert chamfer_distance_parts(predicted, reference, part) == chamfer_distance_parts(predicted, gt, part, 2.0)
        assert chamfer_distance_parts(predicted, reference, part)[0] == chamfer_distance(predicted, gt, radius=2.0)
        assert chamfer_terms_paper(predicted, reference) == chamfer_terms_paper(predicted, gt, radius=2.0)
    assert all(math.isnan(v) for v in chamfer_distance_parts(gt, reference, None)[1:])
    assert chamfer_distance(np.zeros((0, 3)), reference) == math.inf
    with pytest.raises(InvalidInputError, match="NaN"):
        chamfer_distance(gt + np.nan, reference)
    with pytest.raises(InvalidInputError, match="radius must be positive"):
        ReferenceCloud(gt, radius=0.0)
    with pytest.raises(InvalidInputError, match="empty"):
        ReferenceCloud(np.zeros((0, 3)), radius=1.0)


def test_bounding_sphere_radius_of_sphere_points():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    points = 0.07 * d / np.linalg.norm(d, axis=1, keepdims=True) + np.array([1.0, 2.0, 3.0])
    assert bounding_sphere_radius(points) == pytest.approx(0.07, rel=1e-3)


def test_bounding_sphere_radius_of_a_large_cloud():
    """Above 20,000 points only the convex hull's vertices are searched: the same sphere, found faster."""
    rng = np.random.default_rng(2)
    inside = rng.uniform(-1, 1, size=(60_000, 3))
    inside = 0.05 * inside[np.linalg.norm(inside, axis=1) <= 1]
    pole = np.array([[0.0, 0.0, 0.05], [0.0, 0.0, -0.05]])
    points = np.concatenate([inside, pole]) + np.array([0.3, -0.2, 1.0])
    assert len(points) > 20_000
    assert bounding_sphere_radius(points) == pytest.approx(0.05, rel=1e-6)


def test_bounding_sphere_radius_of_flat_and_degenerate_clouds():
    """A flat ground truth (a wall, a constant depth map) is as valid as a round one."""
    rng = np.random.default_rng(1)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    angle = rng.uniform(0, 2 * np.pi, 300)
    disc = np.stack([0.2 * np.cos(angle), 0.2 * np.sin(angle), np.zeros(300)], axis=1)
    assert bounding_sphere_radius(disc @ R.T + 5.0) == pytest.approx(0.2, rel=1e-6)
    square = np.stack(np.meshgrid(np.linspace(-1, 1, 9), np.linspace(-1, 1, 9), [0.4]), -1).reshape(-1, 3)
    assert bounding_sphere_radius(square) == pytest.approx(math.sqrt(2), rel=1e-6)  # axis-aligned plane
    line = np.outer(np.linspace(-0.3, 0.5, 50), [1.0, 2.0, 2.0])
    assert bounding_sphere_radius(line) == pytest.approx(0.4 * 3, rel=1e-9)
    assert bounding_sphere_radius(np.full((4, 3), 2.5)) == 0.0
    with pytest.raises(InvalidInputError, match="no points"):
        bounding_sphere_radius(np.zeros((0, 3)))


def _random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    params = {
        "means": torch.randn(n, 3, generator=g),
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.randn(n, 3, generator=g) - 4,
        "opacities": torch.randn(n, generator=g),
        "sh0": torch.randn(n, 1, 3, generator=g),
        "shN": torch.randn(n, num_sh_bases(degree) - 1, 3, generator=g),
    }
    return Gaussians(params, torch.rand(n, generator=g) > 0.5, degree)


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_ply_round_trip(tmp_path, degree):
    original = _random_gaussians(37, degree)
    path = save_ply(original, tmp_path / "splat.ply")
    loaded = load_ply(path)
    assert loaded.sh_degree == degree
    for name, value in original.params.items():
        torch.testing.assert_close(loaded.params[name].detach(), value.detach(), rtol=0, atol=0)
    assert torch.equal(loaded.from_touch, original.from_touch)


def test_ply_has_the_standard_3dgs_layout(tmp_path):
    g = _random_gaussians(3, 3)
    vertex = PlyData.read(str(save_ply(g, tmp_path / "s.ply")))["vertex"]
    names = [p.name for p in vertex.properties]
    expected = (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(45)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    assert names == expected
    # higher bands channel-major: f_rest_0..14 are red, 15..29 green, 30..44 blue
    assert vertex["f_rest_15"][1] == pytest.approx(g.params["shN"][1, 0, 1].item())
    assert vertex["f_rest_1"][2] == pytest.approx(g.params["shN"][2, 1, 0].item())


def test_ply_without_from_touch_loads_as_vision_gaussians_and_bad_files_name_the_field(tmp_path):
    g = _random_gaussians(4, 0)
    vertex = PlyData.read(str(save_ply(g, tmp_path / "s.ply")))["vertex"].data
    names = [n for n in vertex.dtype.names if n != "from_touch"]
    plain = np.array([tuple(row[n] for n in names) for row in vertex], dtype=[(n, "f4") for n in names])
    PlyData([PlyElement.describe(plain, "vertex")]).write(str(tmp_path / "plain.ply"))
    assert not load_ply(tmp_path / "plain.ply").from_touch.any()
    broken_names = [n for n in names if n != "opacity"]
    broken = np.array([tuple(row[n] for n in broken_names) for row in vertex], dtype=[(n, "f4") for n in broken_names])
    PlyData([PlyElement.describe(broken, "vertex")]).write(str(tmp_path / "broken.ply"))
    with pytest.raises(SceneFormatError, match="opacity"):
        load_ply(tmp_path / "broken.ply")


def test_a_ground_truth_with_a_nan_or_infinite_vertex_is_refused_naming_the_file_and_the_vertex(tmp_path):
    """`evaluate --gt-mesh`: a point cloud with a NaN point crashed in the radius's SVD, and trimesh dropped a
    mesh's NaN vertex and its faces silently; both are refused, naming the first bad vertex."""
    import trimesh

    from tacsplat.reconstruction.evaluation import read_ground_truth

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    vertices = sphere.vertices.copy()
    vertices[3], vertices[7] = np.nan, (0.0, np.inf, 0.0)
    trimesh.PointCloud(vertices).export(tmp_path / "points.ply")
    trimesh.Trimesh(vertices, sphere.faces, process=False).export(tmp_path / "mesh.ply")
    for name in ("points.ply", "mesh.ply"):
        with pytest.raises(SceneFormatError, match=rf"{name} \[vertex 3\]: coordinates \[nan, nan, nan\] are not"):
            read_ground_truth(tmp_path / name)
    # a finite mesh is read as trimesh reads it by default (duplicate vertices merged)
    trimesh.Trimesh(
        sphere.vertices[sphere.faces].reshape(-1, 3), np.arange(3 * len(sphere.faces)).reshape(-1, 3), process=False
    ).export(tmp_path / "soup.ply")
    read = read_ground_truth(tmp_path / "soup.ply")
    assert len(read.vertices) == len(sphere.vertices) and len(read.faces) == len(sphere.faces)


def test_a_ground_truth_of_zero_extent_is_refused_naming_the_file(tmp_path):
    """`evaluate --gt-mesh`: a triangle whose corners coincide, or points all at one place, have a radius of 0 to
    measure distances in: one error naming the file (it was numpy's divide-by-zero warning, then a radius error)."""
    import trimesh

    from tacsplat.reconstruction.evaluation import read_ground_truth

    trimesh.Trimesh(np.full((3, 3), 0.02), [[0, 1, 2]], process=False).export(tmp_path / "triangle.ply")
    trimesh.PointCloud(np.full((5, 3), 0.01)).export(tmp_path / "points.ply")
    for name, count, at in (("triangle.ply", 3, [0.02] * 3), ("points.ply", 5, [0.01] * 3)):
        with pytest.raises(
            SceneFormatError, match=re.escape(f"{name}: no extent: all its {count} vertices lie at {at}")
        ):
            read_ground_truth(tmp_path / name)
    trimesh.PointCloud(np.array([[0.0, 0, 0], [0, 0, 1e-6]])).export(tmp_path / "pair.ply")
    assert len(read_ground_truth(tmp_path / "pair.ply")) == 2  # two points apart: a (small) extent


def test_background_is_fitted_to_a_smooth_border_and_black_for_a_cluttered_one():
    from tacsplat.reconstruction.views import background_image

    h, w = 40, 50
    v = np.linspace(0, 1, h)[:, None, None]
    backdrop = (0.3 + 0.4 * v + 0.1 * v**2) * np.ones((h, w, 3))
    image = backdrop.copy()
    image[10:30, 15:35] = [1.0, 0.0, 0.0]  # the object, away from the border
    np.testing.assert_allclose(background_image(image), backdrop, atol=1e-5)
    cluttered = np.random.default_rng(0).uniform(0, 1, (h, w, 3))
    assert not background_image(cluttered).any()
    np.testing.assert_allclose(background_image(image, color=(0.1, 0.2, 0.3))[5, 7], [0.1, 0.2, 0.3], rtol=1e-6)


def test_a_backdrop_is_fitted_around_an_object_that_crosses_the_border():
    """A close view: the object covers part of the top edge. The backdrop is fitted to the rest of the border (the
    gradient exactly), not given up for black; an object over most of the border leaves no backdrop to fit."""
    from tacsplat.reconstruction.views import background_image, fit_backdrop

    h, w = 40, 50
    v, u = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
    backdrop = (0.3 + 0.4 * v + 0.1 * u * v)[..., None] * np.array([1.0, 0.9, 0.8])
    image = backdrop.copy()
    image[:15, 10:30] = [0.9, 0.1, 0.1]  # the object, across the top edge
    image[:15, 20:30] = [0.1, 0.1, 0.9]
    np.testing.assert_allclose(background_image(image), backdrop, atol=1e-5)
    image[:, :30] = [0.9, 0.1, 0.1]  # over the top, left and bottom edges: most of the border
    assert fit_backdrop(image) is None
    for side in ("left", "top"):  # a whole edge and parts of two more: never a mix of object and backdrop
        for width in range(2, 48 if side == "left" else 38, 4):
            image = backdrop.copy()
            (image[:, :width] if side == "left" else image[:width])[:] = [0.9, 0.1, 0.1]
            fit = fit_backdrop(image)
            assert fit is None or np.abs(fit - backdrop).max() < 0.02, (side, width)


def test_both_chamfer_distances_on_clouds_with_known_distances():
    """Two parallel planes of points 0.1 apart (every nearest neighbour at 0.1): the design's CD is the
    mean unsquared distance each way, halved = 0.1; the paper's is the mean squared distance each way,
    summed = 2 * 0.01. A radius of 2 divides every distance by 2 first."""
    from tacsplat.reconstruction.metrics import chamfer_distance, chamfer_terms_paper

    def chamfer_distance_paper(*args, **kwargs):
        return sum(chamfer_terms_paper(*args, **kwargs))

    g = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0), indexing="ij"), -1).reshape(-1, 2)
    gt = np.column_stack([g, np.zeros(len(g))])
    pred = gt + [0.0, 0.0, 0.1]
    assert chamfer_distance(pred, gt) == pytest.approx(0.1)
    assert chamfer_distance_paper(pred, gt) == pytest.approx(0.02)
    assert chamfer_distance(pred, gt, radius=2.0) == pytest.approx(0.05)
    assert chamfer_distance_paper(pred, gt, radius=2.0) == pytest.approx(2 * 0.05**2)
    # an outlier 3 away weighs far more in the paper's squared form: one of 26 predicted points
    with_outlier = np.vstack([pred, [[0.0, 0.0, 3.0]]])
    assert chamfer_distance(with_outlier, gt) == pytest.approx(0.5 * ((25 * 0.1 + 3.0) / 26 + 0.1))
    assert chamfer_distance_paper(with_outlier, gt) == pytest.approx((25 * 0.01 + 9.0) / 26 + 0.01)
    # asymmetric: a predicted cloud covering half the ground truth
    half = pred[g[:, 0] < 2]
    far = np.sqrt(1.0 + 0.01)  # gt points in row 2 are 1 column from row 1's predicted points (and 0.1 below)
    expected = (10 * 0.01 + 5 * far**2 + 5 * (4 + 0.01) + 5 * (9 + 0.01)) / 25 + 0.01
    assert chamfer_distance_paper(half, gt) == pytest.approx(expected)
    assert chamfer_terms_paper(half, gt) == pytest.approx((0.01, expected - 0.01))  # accuracy, completeness
    assert chamfer_distance_paper(np.zeros((0, 3)), gt) == float("inf")


def test_seen_by_cameras_marks_the_surface_a_camera_sees_and_not_the_far_side():
    import trimesh

    from tacsplat.datasets.records import Frame
    from tacsplat.geometry import look_at
    from tacsplat.reconstruction.evaluation import seen_by_cameras
    from tacsplat.reconstruction.views import mesh_depth
    from tacsplat.types import CameraIntrinsics

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    intrinsics = CameraIntrinsics(np.array([[80.0, 0, 32], [0, 80.0, 32], [0, 0, 1]]), 64, 64)

    def camera(i, eye):
        return Frame(i, f"{i}.png", look_at(eye, (0, 0, 0), up=(0, 1, 0) if eye[2] else (0, 0, 1)), "test", intrinsics)

    top, bottom, side = camera(0, (0, 0, 0.5)), camera(1, (0, 0, -0.5)), camera(2, (0.5, 0, 0))
    points = {f.id: depth_to_points(mesh_depth(sphere, f), f.intrinsics.K, f.T_world_cam) for f in (top, bottom, side)}
    seen = seen_by_cameras(sphere, points, [top], radius=0.1)
    assert seen[0].mean() > 0.99  # what the camera itself sees
    assert not seen[1].any()  # the far side
    # from the side, the upper half is in view of the top camera (above its tangent circle at z = r^2 / d = 0.02)
    expected = points[2][:, 2] > 0.02
    assert (seen[2] == expected).mean() > 0.99


def test_comparison_picture_shows_the_signed_depth_error_and_what_training_cameras_see(tmp_path):
    import cv2

    from tacsplat.reconstruction.evaluation import save_comparison

    gt_depth = np.zeros((4, 5))
    gt_depth[1:3, 1:4] = 1.0  # six surface pixels
    depth = gt_depth.copy()
    depth[1, 1] = 1.2  # behind the truth
    depth[1, 2] = 0.8  # in front of it
    depth[2, 3] = 0.0  # a hole
    depth[0, 0] = 1.0  # surface where the truth has none
    seen = np.array([True, True, False, True, True, True])  # along the valid pixels, row by row
    rgb = np.zeros((4, 5, 3))
    save_comparison(tmp_path / "v.png", rgb, rgb, depth, gt_depth, radius=1.0, seen=seen)
    picture = cv2.cvtColor(cv2.imread(str(tmp_path / "v.png")), cv2.COLOR_BGR2RGB)
    assert picture.shape == (8, 15, 3)
    error, coverage = picture[:4, 10:], picture[4:, 10:]
    assert tuple(error[1, 1]) == (255, 0, 0) and tuple(error[1, 2]) == (0, 0, 255)  # saturated at 0.1 radius
    assert tuple(error[2, 1]) == (255, 255, 255)  # exact
    assert tuple(error[2, 3]) == (0, 255, 0) and tuple(error[0, 0]) == (64, 64, 64)
    assert tuple(coverage[1, 3]) == (230, 0, 200) and tuple(coverage[1, 1]) == (200, 200, 200)
    assert tuple(coverage[0, 0]) == (0, 0, 0)
