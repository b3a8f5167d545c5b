"""Reconstruction pushed to extremes: Gaussians that run away under a learning rate far too high, size options past
what memory holds, a ground-truth mesh in other units, test views that see no object, and a mesh far from the
origin."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from plyfile import PlyData

from tacsplat.cli import main
from tacsplat.datasets import SceneMeta, SceneWriter
from tacsplat.geometry import invert_pose, look_at
from tacsplat.reconstruction import trainer
from tacsplat.reconstruction.config import TrainConfig
from tacsplat.reconstruction.meshing import ExtractedMesh, mesh_ply
from tacsplat.reconstruction.raster.rendering import rasterization
from tacsplat.reconstruction.trainer import Trainer
from tacsplat.types import CameraIntrinsics

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import RADIUS, build_sphere_scene, one_error_line, sphere_depth, sphere_gaussians  # noqa: E402

TINY_RUN = ["--sh-degree", "0", "--lambda-s", "0", "--init.no-use-sfm", "--init.num-random-points", "200", "--quiet"]


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return build_sphere_scene(tmp_path_factory.mktemp("scenes") / "sphere", size=16, train_views=3, test_views=1)


@pytest.fixture(scope="module")
def tiny_run(tiny_scene, tmp_path_factory):
    run = tmp_path_factory.mktemp("runs") / "run"
    assert main(["reconstruct", str(tiny_scene), "--out", str(run), "--iterations", "2", *TINY_RUN]) == 0
    return run


# --------------------------------------------------------------------------- Gaussians that run away


def test_a_position_rate_far_too_high_ends_with_one_error_naming_it_and_saves_nothing(tiny_scene, tmp_path, capsys):
    """--lr-means 1e3 moves the Gaussians hundreds of metres a step, every value finite: one error says that
    training diverged, that the Gaussians ran away, and names the rate given; exit 1, no checkpoint, no splat."""
    run = tmp_path / "run"
    argv = ["reconstruct", str(tiny_scene), "--out", str(run), "--iterations", "4", "--lr-means", "1e3"]
    assert main([*argv, *TINY_RUN]) == 1
    one_error_line(capsys, "training diverged at step 4", "ran away", "--lr-means 1000 (default 0.00016)")
    assert not (run / "checkpoint.pt").exists() and not (run / "splat.ply").exists()


@pytest.mark.parametrize("moved, fails", [(0.4, False), (0.6, True)])
def test_training_stops_when_most_gaussians_lie_far_beyond_the_scene(
    tiny_scene, tmp_path, capsys, monkeypatch, moved, fails
):
    """After step 1, a share ``moved`` of the Gaussians is moved to twice RUNAWAY_FACTOR times the scene's reach:
    under half of them is no error (a few far Gaussians are no run-away), over half is one; the checkpoint of step 1
    stays."""
    real_step = Trainer.train_step

    def far_step(self):
        terms = real_step(self)
        if self.step == 2:
            means = self.gaussians.params["means"].data
            means[: int(moved * len(means))] += 2 * trainer.RUNAWAY_FACTOR * self.reach
        return terms

    monkeypatch.setattr(Trainer, "train_step", far_step)
    run = tmp_path / "run"
    argv = ["reconstruct", str(tiny_scene), "--out", str(run), "--iterations", "3", "--checkpoint-every", "1"]
    assert main([*argv, *TINY_RUN]) == (1 if fails else 0)
    if fails:
        one_error_line(capsys, "training diverged at step 2", "ran away", "--lr-*")
        assert torch.load(run / "checkpoint.pt", weights_only=False)["step"] == 1
    else:
        assert (run / "splat.ply").is_file()


# --------------------------------------------------------------------------- size options past what memory holds


@pytest.mark.parametrize(
    "option, largest, cost",
    [("--touch-candidates", 1024, "25 MB"), ("--init.num-random-points", 1_000_000, "about 3 GB")],
)
def test_size_options_past_their_memory_bound_are_one_usage_error_saying_the_cost(
    tiny_scene, tmp_path, capsys, monkeypatch, option, largest, cost
):
    """One above the largest: exit 2 naming the option, its range and what the largest costs, before any training
    (no Trainer is made) and with nothing made on disk; the largest itself is a valid setting."""

    def no_training(*args, **kwargs):
        raise AssertionError("training started")

    monkeypatch.setattr(Trainer, "__init__", no_training)
    run = tmp_path / "run"
    assert main(["reconstruct", str(tiny_scene), "--out", str(run), option, str(largest + 1), "--quiet"]) == 2
    one_error_line(capsys, option, f"to {largest}", cost, f"got {largest + 1}", prefix="")
    assert not run.exists()
    field = option[2:].replace("-", "_")
    config = TrainConfig()
    owner, name = (config.init, field[5:]) if field.startswith("init.") else (config, field)
    setattr(owner, name, largest)
    assert config.problem() is None


# --------------------------------------------------------------------------- a ground truth in other units


def _sphere_mesh(path: Path, radius: float) -> Path:
    trimesh.creation.icosphere(subdivisions=3, radius=radius).export(str(path))
    return path


def test_evaluate_refuses_a_gt_mesh_in_millimetres_naming_the_option_and_both_sizes(tiny_run, tmp_path, capsys):
    """The sphere's mesh in millimetres (radius 50, the cameras 0.25 m away): exit 2, one error naming --gt-mesh,
    the mesh's radius and the cameras' distance; metrics.json is left as it was."""
    before = (tiny_run / "metrics.json").read_bytes()
    mesh = _sphere_mesh(tmp_path / "mm.ply", RADIUS * 1000)
    assert main(["evaluate", str(tiny_run), "--gt-mesh", str(mesh)]) == 2
    one_error_line(capsys, "--gt-mesh", str(mesh), "radius is 50 m", "0.25 m", "wrong units?", prefix="")
    assert (tiny_run / "metrics.json").read_bytes() == before


@pytest.mark.parametrize("scale, refused", [(1.0, False), (1e-3, True), (1e3, True)])
def test_a_gt_mesh_or_cloud_far_from_the_scene_s_size_is_refused_and_one_of_its_size_is_not(
    tiny_scene, tmp_path, scale, refused
):
    """Metres: measured; a thousandth (under a pixel from every camera) or a thousand times (the cameras deep
    inside it): a usage error naming --gt-mesh, for a mesh and for its vertices as a point cloud."""
    from tacsplat.datasets import Scene
    from tacsplat.errors import UsageError
    from tacsplat.reconstruction.evaluation import load_ground_truth

    scene = Scene.load(tiny_scene)
    mesh = _sphere_mesh(tmp_path / "gt.ply", RADIUS * scale)
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(trimesh.load(str(mesh)).vertices).export(str(cloud))
    for path in (mesh, cloud):
        if refused:
            with pytest.raises(UsageError, match="--gt-mesh: .*wrong units"):
                load_ground_truth(scene, scene.split("test"), path)
        else:
            assert load_ground_truth(scene, scene.split("test"), path).radius == pytest.approx(RADIUS, rel=1e-3)


def test_a_forward_facing_captures_mesh_in_metres_is_measured(tmp_path):
    """Cameras side by side looking one way (the scene's centre is theirs): a 3 x 2 x 1 m scan 3.5 m in front is
    19 times the cameras' spread from that centre, and metres; the same in millimetres is refused."""
    from tacsplat.datasets import Scene
    from tacsplat.errors import UsageError
    from tacsplat.reconstruction.evaluation import check_gt_size
    from tacsplat.reconstruction.metrics import bounding_sphere_radius

    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    with SceneWriter.create(tmp_path / "ff", CameraIntrinsics(K, 64, 48), SceneMeta("real", "room")) as writer:
        for k, (x, y) in enumerate((x, y) for x in (-0.15, 0.0, 0.15) for y in (-0.1, 0.0, 0.1)):
            T = np.eye(4)
            T[:3, 3] = [x, y, 0.0]
            writer.add_frame(np.full((48, 64, 3), 128, np.uint8), T, "test" if k % 4 == 3 else "train")
    scene = Scene.load(tmp_path / "ff")
    scan = trimesh.creation.box([3.0, 2.0, 1.0])
    scan.apply_translation([0.0, 0.0, 3.5])
    check_gt_size(scene, "scan.ply", scan.vertices, bounding_sphere_radius(scan.vertices))
    with pytest.raises(UsageError, match="wrong units"):
        check_gt_size(scene, "scan.ply", 1000 * scan.vertices, 1000 * bounding_sphere_radius(scan.vertices))


# --------------------------------------------------------------------------- test views that see no object


@pytest.fixture(scope="module")
def blind_test_scene(tmp_path_factory) -> Path:
    """The sphere seen by three training views and one test view whose ground-truth depth shows no surface (as a
    needle's does at a few pixels), with the sphere's mesh as the scene's gt/mesh.ply."""
    path, size = tmp_path_factory.mktemp("scenes") / "blind", 16
    K = np.array([[20.0, 0, size / 2], [0, 20.0, size / 2], [0, 0, 1.0]])
    gaussians = sphere_gaussians()
    writer = SceneWriter.create(path, CameraIntrinsics(K, size, size), SceneMeta("sim", "synthetic-sphere"))
    with writer:
        for k, split in enumerate(["train", "train", "train", "test"]):  # (the test view's gt depth: none)
            eye = 0.25 * np.array([math.cos(2.1 * k), math.sin(2.1 * k), 0.3])
            T_world_cam = look_at(eye, np.zeros(3))
            viewmat = torch.tensor(invert_pose(T_world_cam))[None]
            background = torch.zeros(1, 3, dtype=torch.float64)
            image, _, _ = rasterization(
                *gaussians, viewmat, torch.tensor(K)[None], size, size, backgrounds=background, backend="torch"
            )
            rgb = (np.clip(image[0].numpy(), 0, 1) * 255).round().astype(np.uint8)
            depth = sphere_depth(K, T_world_cam, size, size) * (split == "train")
            writer.add_frame(rgb, T_world_cam, split, gt_depth=depth)
        writer.set_gt_mesh(trimesh.creation.icosphere(subdivisions=3, radius=RADIUS))
    return path


def test_test_views_that_see_no_object_are_measured_against_the_scene_s_mesh_and_the_warning_says_so(
    blind_test_scene, tmp_path, capsys
):
    """The test view's gt depth shows no surface: the warning says so (not that there is no gt/ depth), cd is null,
    and cd_paper, gt_source and gt_radius come from the scene's mesh, as evaluate --gt-mesh with that mesh gives
    them."""
    run = tmp_path / "run"
    assert main(["reconstruct", str(blind_test_scene), "--out", str(run), "--iterations", "2", *TINY_RUN]) == 0
    err = capsys.readouterr().err
    assert "the test views' ground-truth depth (gt/depth/) shows no surface" in err and "cd is NaN" in err, err
    assert "no gt/ depth" not in err, err
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["cd"] is None and metrics["cd_paper"] > 0
    assert metrics["gt_source"] == "scene gt/" and metrics["gt_radius"] == pytest.approx(RADIUS, rel=1e-3)
    assert main(["evaluate", str(run), "--gt-mesh", str(blind_test_scene / "gt" / "mesh.ply")]) == 0
    given = json.loads((run / "metrics.json").read_text())
    assert given["cd_paper"] == pytest.approx(metrics["cd_paper"]) and given["gt_radius"] == metrics["gt_radius"]


# --------------------------------------------------------------------------- a mesh far from the origin


@pytest.mark.parametrize("offset, precision", [(0.0, "f4"), (5e4, "f8")])
def test_an_exported_mesh_far_from_the_origin_is_written_as_the_mesh_it_is(tmp_path, offset, precision):
    """A 5 cm sphere of 1 mm voxels: near the origin its vertices are float32, 50 km away float64, and the file
    read back holds the mesh's vertices to a thousandth of a voxel (float32 there: 4 mm steps, vertices merged)."""
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    mesh.vertices = mesh.vertices + offset
    mesh.visual.vertex_colors = np.full((len(mesh.vertices), 4), 200, np.uint8)
    extracted = ExtractedMesh(mesh, np.ones(len(mesh.vertices), bool), voxel=1e-3)
    path = tmp_path / "mesh.ply"
    with open(path, "wb") as f:
        mesh_ply(extracted).write(f)
    vertex = PlyData.read(str(path))["vertex"]
    assert vertex.data.dtype["x"] == np.dtype(precision).newbyteorder("<")
    written = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float64)
    assert np.abs(written - mesh.vertices).max() <= 1e-6
    assert len(trimesh.load(str(path), force="mesh").vertices) == len(mesh.vertices)
