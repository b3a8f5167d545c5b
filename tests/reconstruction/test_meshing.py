"""Meshes out of a reconstruction: TSDF fusion of depth and touches, marching cubes, the mesh metrics, `export mesh`."""

from __future__ import annotations

import copy
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from plyfile import PlyData

from tacsplat.cli import main
from tacsplat.datasets import SceneWriter
from tacsplat.reconstruction.meshing import TSDFVolume, seal_hollows, sphere_cameras
from tacsplat.reconstruction.metrics import mesh_metrics

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import build_sphere_scene, sphere_depth  # noqa: E402

R = 0.05  # metres: the sphere of recon_synthetic


VOXEL = 0.025 * R


@pytest.fixture(scope="module")
def sphere_volume() -> TSDFVolume:
    """A TSDF of the sphere of radius R at the origin fused from exact depth maps all around it (24 views)."""
    voxel, views, extent = VOXEL, 24, 1.2 * R
    volume = TSDFVolume(np.full(3, -extent), voxel, (int(np.ceil(2 * extent / voxel)),) * 3, 3 * voxel)
    for frame in sphere_cameras(np.zeros(3), extent, views, 96):
        depth = sphere_depth(frame.intrinsics.K, frame.T_world_cam, 96, 96).astype(np.float64)
        rgb = np.full((96, 96, 3), 0.25)
        volume.integrate_depth(depth, rgb, frame.intrinsics.K, frame.T_world_cam)
    return volume


def test_fused_depth_of_a_sphere_is_a_watertight_mesh_on_it_with_outward_normals(sphere_volume):
    voxel = VOXEL
    mesh = sphere_volume.mesh()
    assert mesh.is_watertight and mesh.body_count == 1
    radii = np.linalg.norm(mesh.vertices, axis=1)
    assert np.abs(radii - R).max() < voxel and np.abs(radii - R).mean() < 0.2 * voxel  # (nearest-pixel depth)
    assert np.all((mesh.vertex_normals * mesh.vertices).sum(axis=1) > 0)  # outward
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * R**3, rel=0.02)
    np.testing.assert_allclose(mesh.visual.vertex_colors[:, :3], 64, atol=1)  # the views' colour, 0.25
    metrics = mesh_metrics(
        mesh, trimesh.creation.icosphere(subdivisions=5, radius=R), R, samples=20_000, targets=400_000
    )
    assert metrics["mesh_fscore_1"] > 0.99 and metrics["mesh_cd"] < 0.005 and metrics["mesh_watertight"]
    assert metrics["mesh_normal_consistency"] > 0.97  # (marching cubes' facets)


def test_touch_points_move_the_surface_where_they_landed(sphere_volume):
    """A tactile map is fused as points along their normals: a patch touched 3 % inside the seen surface pulls
    the mesh there, and nowhere else."""
    voxel = VOXEL
    volume = copy.deepcopy(sphere_volume)
    d = np.random.default_rng(0).normal(size=(40_000, 3))  # a contact patch is dense: one point per gel pixel
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    cap = d[d[:, 2] > np.cos(np.radians(20))]  # a patch around the top
    volume.integrate_points(0.97 * R * cap, cap, weight=24.0)  # (as extract_mesh weighs them: all views' weight)
    mesh = volume.mesh()
    radii = np.linalg.norm(mesh.vertices, axis=1)
    polar = np.degrees(np.arccos(mesh.vertices[:, 2] / radii))
    assert np.abs(radii[polar < 12] - 0.97 * R).max() < voxel
    assert np.abs(radii[polar > 40] - R).max() < voxel
    assert mesh.is_watertight


def test_a_hollow_behind_a_narrow_hole_is_sealed_and_a_wide_notch_stays_open():
    """A ball (radius 20 voxels) with a hollow inside (radius 8) that reaches the outside through a tunnel 2 voxels
    wide, and a notch 14 voxels wide cut into its other side: sealing with a reach of 3 voxels fills the hollow
    and the tunnel and leaves the notch and the outside alone."""
    x, y, z = np.meshgrid(*[np.arange(64) - 31.5] * 3, indexing="ij")
    r = np.sqrt(x**2 + y**2 + z**2)
    hollow = r < 8
    tunnel = (x > 0) & (np.abs(y) < 1) & (np.abs(z) < 1)
    notch = (x < -12) & (np.abs(y) < 7)
    field = np.where((r < 20) & ~hollow & ~tunnel & ~notch, -1.0, 1.0).astype(np.float32)
    sealed = seal_hollows(field, 3.0)
    assert np.all(sealed[hollow] == -1) and np.all(sealed[tunnel & (r < 18)] == -1)  # (to within its mouth)
    assert np.all(sealed[r > 21] == 1)  # the outside
    assert np.all(sealed[notch & (x < -14) & (np.abs(y) < 3)] == 1)  # the notch, away from its walls
    assert np.array_equal(seal_hollows(field, 0.0), field)
    assert np.array_equal(sealed[field < 0], field[field < 0])  # the inside is only ever added to


def test_mesh_metrics_of_the_truth_and_of_a_grown_copy():
    truth = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    same = mesh_metrics(truth, truth, 1.0, samples=20_000, targets=400_000)
    assert same["mesh_fscore_1"] > 0.99 and same["mesh_cd"] < 0.004 and same["mesh_normal_consistency"] > 0.999
    grown = mesh_metrics(truth.copy().apply_scale(1.03), truth, 1.0, samples=20_000, targets=400_000)
    assert grown["mesh_fscore_1"] < 0.01 and grown["mesh_fscore_2"] < 0.01 and grown["mesh_fscore_5"] > 0.99
    assert grown["mesh_cd"] == pytest.approx(0.03, rel=0.05)
    points = mesh_metrics(
        truth, np.asarray(truth.vertices), 1.0, samples=20_000, targets=400_000
    )  # a ground truth of points
    assert np.isnan(points["mesh_normal_consistency"]) and points["mesh_fscore_5"] > 0.99


def test_mesh_fscores_split_into_the_seen_surface_and_the_rest():
    truth = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    lower_grown = truth.copy()
    lower_grown.vertices[lower_grown.vertices[:, 2] < -0.2] *= 1.1  # wrong by 0.1 radii below z = -0.2
    split = mesh_metrics(lower_grown, truth, 1.0, samples=20_000, targets=400_000, seen_by=lambda p: p[:, 2] > 0)
    assert split["mesh_fscore_5_seen"] > 0.99 and split["mesh_fscore_5_unseen"] < 0.5
    assert split["mesh_unseen_fraction"] == pytest.approx(0.5, abs=0.02)
    assert split["mesh_fscore_5_unseen"] < split["mesh_fscore_5"] < split["mesh_fscore_5_seen"]
    assert "mesh_fscore_5_seen" not in mesh_metrics(lower_grown, truth, 1.0, samples=2_000, targets=20_000)
    nothing_seen = mesh_metrics(truth, truth, 1.0, samples=2_000, targets=20_000, seen_by=lambda p: p[:, 2] > 2)
    assert np.isnan(nothing_seen["mesh_fscore_5_seen"]) and nothing_seen["mesh_fscore_5_unseen"] > 0.99


@pytest.fixture(scope="module")
def sphere_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("mesh")
    scene = build_sphere_scene(root / "scene", size=32, train_views=6, test_views=1)
    with SceneWriter.resume(scene) as writer:
        writer.set_gt_mesh(trimesh.creation.icosphere(subdivisions=4, radius=R))
    command = ["reconstruct", str(scene), "--out", str(root / "run"), "--iterations", "60", "--backend", "cpu"]
    assert main(command) == 0
    return root / "run"


@pytest.fixture(scope="module")
def exported(sphere_run) -> dict:
    """``export mesh`` of the run once, to its default path; its printed summary."""
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["export", "mesh", str(sphere_run), "--voxel", "0.04", "--views", "24"]) == 0
    return json.loads(out.getvalue())


def test_export_mesh_writes_a_watertight_colored_mesh_and_its_metrics(sphere_run, exported):
    summary = exported
    assert summary["mesh"] == str(sphere_run / "mesh.ply") and summary["mesh_watertight"] is True
    vertex = PlyData.read(str(sphere_run / "mesh.ply"))["vertex"]
    assert {"nx", "ny", "nz", "red", "green", "blue", "observed"} <= set(vertex.data.dtype.names)
    observed = np.asarray(vertex["observed"])
    assert set(np.unique(observed)) <= {0, 1} and observed.any()  # the training cameras see part of it
    assert 0 < summary["observed_fraction"] <= 1
    mesh = trimesh.load(str(sphere_run / "mesh.ply"), force="mesh")
    assert mesh.is_watertight
    normals = np.stack([np.asarray(vertex[k], np.float64) for k in ("nx", "ny", "nz")], axis=1)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    from_faces = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).vertex_normals  # of outward faces
    assert ((normals * from_faces).sum(axis=1) > 0).mean() > 0.99  # the written normals point outward too
    text = (sphere_run / "metrics.json").read_text()
    assert "NaN" not in text  # (JSON has none: the unseen part's F-score, with nothing unseen, is null)
    metrics = json.loads(text)
    keys = (
        "mesh_fscore_1",
        "mesh_fscore_2",
        "mesh_fscore_5",
        "mesh_fscore_5_seen",
        "mesh_cd",
        "mesh_normal_consistency",
    )
    for key in keys:
        assert np.isfinite(metrics[key]) and metrics[key] == summary[key]


@pytest.mark.parametrize("voxel", ["0.5", "0.002"])  # (0.002: a grid of 1000^3 cells, 11 GiB for one array)
def test_export_mesh_refuses_a_voxel_out_of_range_naming_the_option(sphere_run, capsys, voxel):
    assert main(["export", "mesh", str(sphere_run), "--voxel", voxel]) == 2
    err = capsys.readouterr().err
    assert "--voxel" in err and "must be in [0.005, 0.2]" in err, err


def test_an_exported_mesh_goes_back_into_the_twin_at_its_own_size(sphere_run, exported, tmp_path, capsys):
    """The loop: reconstruct, export, simulate grasps on the export at its own size; the touches lie on it."""
    from tacsplat.datasets import Scene
    from tacsplat.sim.objects import bounding_sphere

    mesh_path = Path(exported["mesh"])
    command = ["sim-capture", "--mesh", str(mesh_path), "--keep-size", "--out", str(tmp_path / "scene")]
    assert main([*command, "--views", "1", "--test-views", "0", "--grasps", "1", "--resolution", "32"]) == 0
    scene = Scene.load(tmp_path / "scene")
    exported = trimesh.load(str(mesh_path), force="mesh")
    assert bounding_sphere(trimesh.load(str(scene.gt_mesh_path), force="mesh"))[1] == pytest.approx(
        bounding_sphere(exported)[1], rel=1e-6
    )
    truth = trimesh.load(str(scene.gt_mesh_path), force="mesh")
    assert truth.area == pytest.approx(exported.area, rel=1e-3)  # the same size, only moved to its sphere's centre
    points = scene.touch_points()
    assert len(points) > 0
    _, distance, _ = trimesh.proximity.closest_point(truth, points)
    assert np.median(distance) < 1e-4
    capsys.readouterr()
    assert main(["sim-capture", "--keep-size", "--out", str(tmp_path / "x")]) == 2
    assert "--keep-size" in capsys.readouterr().err


def test_unreached_pieces_beyond_the_object_sphere_are_cleared_not_blobs_in_the_grid_corners():
    """One view of the sphere, in a grid wider than its image: the grid's corners that no view reached (out of the
    image) were inside, blobs of their own; cleared, they are outside, while the sphere's shadow, which the view
    cannot reach either but which touches the object's sphere, stays inside (the watertight guess behind it)."""
    voxel, extent = 0.05 * R, 1.6 * R
    volume = TSDFVolume(np.full(3, -extent), voxel, (int(np.ceil(2 * extent / voxel)),) * 3, 3 * voxel)
    frame = sphere_cameras(np.zeros(3), R, 1, 64)[0]
    depth = sphere_depth(frame.intrinsics.K, frame.T_world_cam, 64, 64).astype(np.float64)
    volume.integrate_depth(depth, np.full((64, 64, 3), 0.5), frame.intrinsics.K, frame.T_world_cam)
    assert len(volume.mesh().split(only_watertight=False)) > 1  # (the corners: else the test shows nothing)
    volume.clear_blobs(np.zeros(3), 1.05 * R)
    mesh = volume.mesh()
    assert len(mesh.split(only_watertight=False)) == 1 and mesh.is_watertight
    behind = -frame.T_world_cam[:3, 3] / np.linalg.norm(frame.T_world_cam[:3, 3])  # from the camera through the centre
    front = mesh.vertices[mesh.vertices @ behind < -0.1 * R]  # the camera's side: the sphere, nothing further out
    assert len(front) and np.linalg.norm(front, axis=1).max() < R + 2 * voxel
    assert volume.field()[tuple(np.floor((1.3 * R * behind + extent) / voxel).astype(int))] < 0  # the shadow: inside


def test_export_mesh_with_no_fused_camera_is_one_error_naming_cone_deg_and_views(sphere_run, tmp_path, capsys):
    """No camera of --views within --cone-deg of a training camera: nothing would be fused (the mesh was the whole
    voxel cube); an error, and the --out folder it named is not created."""
    out = tmp_path / "new" / "sub" / "m.ply"
    command = ["export", "mesh", str(sphere_run), "--views", "6", "--cone-deg", "1", "--voxel", "0.04"]
    assert main([*command, "--out", str(out)]) == 2  # (a value of an option: a usage error)
    err = capsys.readouterr().err
    assert err.startswith("tacsplat export mesh: error: --cone-deg: ") and "--views" in err
    assert len(err.splitlines()) == 1
    assert not (tmp_path / "new").exists()


def test_export_mesh_refuses_a_path_that_is_not_a_run_and_creates_nothing(tmp_path, capsys):
    (tmp_path / "notrun").mkdir()
    (tmp_path / "notrun" / "a.txt").write_text("x")
    assert main(["export", "mesh", str(tmp_path / "nope" / "typo-run")]) == 1
    assert "typo-run: does not exist: not a reconstruction run directory" in capsys.readouterr().err
    assert main(["export", "mesh", str(tmp_path / "notrun" / "a.txt")]) == 1
    assert "a.txt: is a file: not a reconstruction run directory" in capsys.readouterr().err
    assert main(["export", "mesh", str(tmp_path / "notrun"), "--out", str(tmp_path / "nope2" / "sub" / "m.ply")]) == 1
    assert "not a reconstruction run directory" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notrun"]
    assert [p.name for p in (tmp_path / "notrun").iterdir()] == ["a.txt"]


def test_export_mesh_refuses_an_out_that_is_not_a_ply(sphere_run, tmp_path, capsys):
    """The mesh is written as PLY: PLY bytes in x.obj would mislead every reader."""
    command = ["export", "mesh", str(sphere_run), "--voxel", "0.04", "--views", "24", "--out", str(tmp_path / "x.obj")]
    assert main(command) == 2
    err = capsys.readouterr().err
    assert "--out" in err and ".ply" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def meshed_run(sphere_run, exported, tmp_path_factory) -> Path:
    """A copy of the exported run with its untouched mesh exported too (as ``bench paper --mesh`` leaves it)."""
    import shutil

    from tacsplat.reconstruction.meshing import MeshConfig, export_mesh

    run = tmp_path_factory.mktemp("meshed") / "run"
    shutil.copytree(sphere_run, run, ignore=shutil.ignore_patterns(".tacsplat.lock"))
    config = MeshConfig(voxel=0.04, views=24, touches=False)
    export_mesh(run, run / "mesh-untouched.ply", config, record="mesh_untouched")
    return run


def copy_run(run: Path, to: Path) -> Path:
    import shutil

    shutil.copytree(run, to / "run")
    return to / "run"


def test_evaluate_with_gt_mesh_measures_the_exported_meshes_against_it(meshed_run, tmp_path):
    """`evaluate --gt-mesh X`: the mesh metrics too are against X (they were against the scene's own truth), here a
    point cloud twice the sphere's size: no normals, no seen split."""
    from tacsplat.reconstruction.evaluation import evaluate_run
    from tacsplat.reconstruction.metrics import bounding_sphere_radius

    run = copy_run(meshed_run, tmp_path)
    points = trimesh.creation.icosphere(subdivisions=4, radius=2 * R).vertices
    trimesh.PointCloud(points).export(str(tmp_path / "other.ply"))
    metrics = evaluate_run(run, gt_path=tmp_path / "other.ply")
    assert metrics["gt_source"] == f"points {tmp_path / 'other.ply'}"
    for prefix, name in (("mesh", "mesh.ply"), ("mesh_untouched", "mesh-untouched.ply")):
        mesh = trimesh.load(str(run / name), force="mesh")
        expected = mesh_metrics(mesh, points, bounding_sphere_radius(points))
        assert metrics[f"{prefix}_cd"] == pytest.approx(expected["mesh_cd"])
        assert metrics[f"{prefix}_normal_consistency"] is None and f"{prefix}_fscore_5_seen" not in metrics
    assert json.loads((run / "metrics.json").read_text())["mesh_cd"] == metrics["mesh_cd"]


def test_evaluate_keeps_the_untouched_mesh_metrics(meshed_run, tmp_path):
    """`evaluate` rewrites metrics.json: the `mesh_untouched_*` of `export mesh` stay (measured again from
    mesh-untouched.ply, against the same truth as `mesh_*`)."""
    from tacsplat.reconstruction.evaluation import evaluate_run

    run = copy_run(meshed_run, tmp_path)
    exported = json.loads((run / "metrics.json").read_text())
    assert "mesh_untouched_fscore_5" in exported
    metrics = evaluate_run(run)
    for key in ("mesh_untouched_fscore_5", "mesh_untouched_cd", "mesh_untouched_watertight", "mesh_fscore_5"):
        assert metrics[key] == pytest.approx(exported[key], abs=1e-3), key
    assert json.loads((run / "metrics.json").read_text())["mesh_untouched_cd"] == metrics["mesh_untouched_cd"]


def test_an_interrupted_export_leaves_no_mesh_file_without_its_metrics(meshed_run, tmp_path, monkeypatch):
    """The mesh file marks a run's meshes done (`bench paper --mesh`): it appears only after its metrics are in
    metrics.json. Interrupted while measuring, or while recording them: no mesh.ply (it was there, metrics missing)."""
    import tacsplat.reconstruction.meshing as meshing

    run = copy_run(meshed_run, tmp_path)
    (run / "mesh.ply").unlink()
    before = (run / "metrics.json").read_text()
    config = meshing.MeshConfig(voxel=0.04, views=24)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    for where in ("mesh_metrics", "atomic_write"):  # (atomic_write: metrics.json's)
        with monkeypatch.context() as patch:
            patch.setattr(meshing, where, interrupted)
            with pytest.raises(KeyboardInterrupt):
                meshing.export_mesh(run, None, config)
        assert sorted(p.name for p in run.glob("mesh*")) == ["mesh-untouched.ply"], where
        assert (run / "metrics.json").read_text() == before


def test_a_run_with_meshes_is_complete_only_with_both_meshes(tmp_path):
    """`bench paper --mesh` exports mesh-untouched.ply, then mesh.ply: a lone mesh.ply (`tacsplat export mesh` by
    hand) lacks the untouched mesh and its metrics."""
    from tacsplat.apps.batch import ReconstructJob

    job = ReconstructJob(out=tmp_path, scene=tmp_path / "scene", export_mesh=True)
    (tmp_path / "metrics.json").write_text("{}")
    (tmp_path / "mesh.ply").write_text("ply")
    assert not job.complete()
    (tmp_path / "mesh-untouched.ply").write_text("ply")
    assert job.complete() and ReconstructJob(out=tmp_path, scene=tmp_path / "scene").complete()
