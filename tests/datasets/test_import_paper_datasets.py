"""The paper's datasets as distributed (miniature copies made here): Shiny Blender's ground truth through
`import blender`, Glossy Synthetic through `import nero`; poses, intrinsics and depth round-trip."""

from __future__ import annotations

import os
import pickle
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tacsplat.cli import main
from tacsplat.datasets import Scene
from tacsplat.datasets.blender import import_blender
from tacsplat.datasets.nero import import_nero
from tacsplat.errors import SceneFormatError
from tacsplat.geometry import invert_pose, opencv_to_opengl
from tacsplat.reconstruction.evaluation import ground_truth_normals

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders

from paper_datasets import (  # noqa: E402
    GLOSSY_K,
    RADIUS,
    SIZE,
    make_glossy_synthetic,
    make_shiny_blender,
    ring_pose,
    sphere_depth,
    sphere_normals,
)

# a disparity of 16 bits resolves depth z to (1 + z)^2 / 65535 (4e-4 units at z = 4): half of that, plus rounding
DISPARITY_DEPTH_TOLERANCE = 3e-4
NERO_DEPTH_TOLERANCE = 15.0 / 65535  # N-depth.png's step


def _project(points: np.ndarray, K: np.ndarray, world_to_camera: np.ndarray) -> np.ndarray:
    """Pixel coordinates [N, 2] (centres at +0.5) of world points under an OpenCV world-to-camera pose."""
    cam = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    return (cam @ K.T)[:, :2] / cam[:, 2:]


def _points_on_sphere(n: int = 50) -> np.ndarray:
    d = np.random.default_rng(5).normal(size=(n, 3))
    return RADIUS * d / np.linalg.norm(d, axis=1, keepdims=True)


def test_shiny_blender_keeps_test_depth_and_train_points_as_ground_truth(tmp_path):
    src = make_shiny_blender(tmp_path, n_train=6, n_test=3)
    scene = Scene.load(import_blender(src, tmp_path / "scene", background_rgb=(0, 0, 0), scale=0.05))
    test = scene.split("test")
    assert len(test) == 3 and len(scene.split("train")) == 6
    assert set(scene.gt_depth_files) == {f.id for f in test}  # the test views' depth, not the train views'
    for k, frame in enumerate(test):
        truth = sphere_depth(frame.intrinsics.K, ring_pose(k + 0.5, 3))  # the dataset's units
        np.testing.assert_array_equal(scene.gt_depth(frame) > 0, truth > 0)
        np.testing.assert_allclose(scene.gt_depth(frame), 0.05 * truth, atol=0.05 * DISPARITY_DEPTH_TOLERANCE)
        # the normal maps: world-frame unit vectors as decoded, turned into the camera frame for the evaluation
        world = sphere_normals(frame.intrinsics.K, ring_pose(k + 0.5, 3), truth)
        np.testing.assert_allclose(scene.gt_normal(frame), world, atol=0.01)
        camera = ground_truth_normals(scene, frame, scene.gt_depth(frame))
        from_depth = ground_truth_normals(_without_normals(scene), frame, scene.gt_depth(frame))
        inside = (cv2.erode((truth > 0).astype(np.uint8), np.ones((3, 3))) > 0) & (np.abs(from_depth).sum(-1) > 0)
        cos = (camera[inside] * from_depth[inside]).sum(-1)
        assert inside.sum() > 10 and np.degrees(np.arccos(np.clip(cos, -1, 1))).mean() < 10
    points = scene.gt_points()  # the train views' depth back-projected (at most 5000 per view)
    assert 0 < len(points) <= 6 * 5000
    np.testing.assert_allclose(np.linalg.norm(points / 0.05, axis=1), RADIUS, atol=DISPARITY_DEPTH_TOLERANCE * 2)
    assert scene.meta.extra["ground_truth"].startswith("disparity maps")


class _without_normals:
    """A scene seen without its normal maps (the evaluation then takes normals from the depth)."""

    def __init__(self, scene):
        self.scene = scene

    def gt_normal(self, frame):
        return None


def test_shiny_blender_cameras_reproject_as_the_dataset_does(tmp_path):
    """The dataset's convention (multinerf, the official code): OpenGL camera-to-world, f from camera_angle_x,
    principal point at the image centre, pixel centres at +0.5."""
    src = make_shiny_blender(tmp_path, n_train=2, n_test=2)
    scene = Scene.load(import_blender(src, tmp_path / "scene"))
    points = _points_on_sphere()
    for k, frame in enumerate(scene.split("train")):
        c2w_gl = opencv_to_opengl(ring_pose(k, 2))  # what transforms_train.json holds
        local = (points - c2w_gl[:3, 3]) @ c2w_gl[:3, :3]  # OpenGL camera axes: x right, y up, looking down -z
        f = frame.intrinsics.K[0, 0]
        theirs = np.stack([f * local[:, 0] / -local[:, 2] + SIZE / 2, -f * local[:, 1] / -local[:, 2] + SIZE / 2], 1)
        ours = _project(points, frame.intrinsics.K, invert_pose(frame.T_world_cam))
        np.testing.assert_allclose(ours, theirs, atol=1e-6)


def test_shiny_blender_disparity_of_the_wrong_kind_is_named(tmp_path):
    src = make_shiny_blender(tmp_path, n_train=2, n_test=1)
    cv2.imwrite(str(src / "test" / "r_0_disp.tiff"), np.zeros((SIZE, SIZE, 3), np.uint8))
    with pytest.raises(SceneFormatError, match=r"r_0_disp\.tiff.*16-bit"):
        import_blender(src, tmp_path / "scene")
    assert not (tmp_path / "scene").exists()


def test_nero_import_cameras_depth_split_and_points(tmp_path):
    src = make_glossy_synthetic(tmp_path)
    scene = Scene.load(import_nero(src, tmp_path / "scene", background_rgb=(0, 0, 255), scale=0.04))
    train, test = scene.split("train"), scene.split("test")
    assert len(train) == 8 and len(test) == 4
    assert scene.meta.extra["importer"] == "nero" and scene.meta.object == "bell"
    test_ids = [0, 2, 4, 9]  # NeRO's split lists them unsorted; the scene keeps their numeric order
    train_ids = [i for i in range(12) if i not in test_ids]
    points = _points_on_sphere()
    for frame, view in zip(train + test, train_ids + test_ids):
        w2c = np.vstack([invert_pose(ring_pose(view, 12, distance=3.0))[:3], [0, 0, 0, 1]])  # what the pickle holds
        theirs = _project(points, GLOSSY_K, w2c)  # NeRO's project_points: K (R p + t)
        ours = _project(0.04 * points, frame.intrinsics.K, invert_pose(frame.T_world_cam))
        np.testing.assert_allclose(ours, theirs, atol=1e-4)  # (the pickle's float32)
        image = scene.load_image(frame)
        truth = sphere_depth(GLOSSY_K, ring_pose(view, 12, distance=3.0))
        np.testing.assert_allclose(image[truth <= 0], np.broadcast_to([0, 0, 1.0], image[truth <= 0].shape))
        if frame.split == "test":
            np.testing.assert_array_equal(scene.gt_depth(frame) > 0, truth > 0)
            np.testing.assert_allclose(scene.gt_depth(frame), 0.04 * truth, atol=0.04 * NERO_DEPTH_TOLERANCE)
        else:
            assert scene.gt_depth(frame) is None
    np.testing.assert_allclose(np.linalg.norm(scene.gt_points(), axis=1), 0.04 * RADIUS, rtol=1e-6)
    assert len(scene.gt_points()) == 3000


def test_nero_without_eval_points_builds_them_from_the_test_depth_as_nero_does(tmp_path):
    src = make_glossy_synthetic(tmp_path, eval_points=False)
    scene = Scene.load(import_nero(src, tmp_path / "scene"))
    points = scene.gt_points()
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), RADIUS, atol=0.01)
    keys = np.floor(points / 0.01).astype(int)
    assert len(np.unique(keys, axis=0)) >= 0.95 * len(points)  # about one point per 0.01 voxel


def test_nero_import_errors_name_the_file(tmp_path, capsys):
    src = make_glossy_synthetic(tmp_path)
    os.replace(tmp_path / "synthetic_split_128.pkl", tmp_path / "split.pkl")
    assert main(["import", "nero", str(src), "--out", str(tmp_path / "a")]) == 1
    err = capsys.readouterr().err
    assert "synthetic_split_128.pkl" in err and "--split" in err and "Traceback" not in err
    assert main(["import", "nero", str(src), "--out", str(tmp_path / "a"), "--split", str(tmp_path / "split.pkl")]) == 0

    class Payload:  # a pickle that would call a function when loaded
        def __reduce__(self):
            return (os.getcwd, ())

    (src / "3-camera.pkl").write_bytes(pickle.dumps(Payload()))
    with pytest.raises(SceneFormatError, match=r"3-camera\.pkl.*refusing to load posix\.getcwd"):
        import_nero(src, tmp_path / "b", split=tmp_path / "split.pkl")
    (src / "3-camera.pkl").write_bytes(pickle.dumps((np.eye(3)[:, :3], GLOSSY_K)))
    with pytest.raises(SceneFormatError, match=r"3-camera\.pkl.*3x4 pose"):
        import_nero(src, tmp_path / "b", split=tmp_path / "split.pkl")
    (src / "3-camera.pkl").unlink()
    with pytest.raises(SceneFormatError, match=r"split\.pkl.*views the dataset does not have: 3"):
        import_nero(src, tmp_path / "b", split=tmp_path / "split.pkl")
    assert not (tmp_path / "b").exists()


@pytest.mark.parametrize(
    "entry, value, words",
    [
        ((0, 2), 10.0 * SIZE, r"K\[0\]\[2\] \(cx\) .*the principal point must be inside the image"),
        ((1, 2), -1.0, r"K\[1\]\[2\] \(cy\) .*the principal point must be inside the image"),
        ((0, 0), 1e-3, r"K\[0\]\[0\] \(fl_x\) .*field of view"),
        ((0, 1), 0.5, "not a zero-skew pinhole camera matrix"),
    ],
    ids=["cx off the image", "cy negative", "a field of view no camera has", "skew"],
)
def test_a_camera_the_scene_cannot_hold_names_its_pickle_and_K(tmp_path, entry, value, words):
    src = make_glossy_synthetic(tmp_path, views=5, test=(0, 2), eval_points=False)
    K = GLOSSY_K.copy()
    K[entry] = value
    w2c = invert_pose(ring_pose(3, 5, distance=3.0))[:3]
    (src / "3-camera.pkl").write_bytes(pickle.dumps((w2c, K)))
    with pytest.raises(SceneFormatError, match=words) as info:
        import_nero(src, tmp_path / "scene")
    assert info.value.path == src / "3-camera.pkl" and info.value.field == "K"
    assert not (tmp_path / "scene").exists()


def test_a_pose_off_rigid_by_rounding_is_made_rigid_and_one_too_far_names_its_pickle(tmp_path):
    src = make_glossy_synthetic(tmp_path, views=5, test=(0, 2), eval_points=False)
    w2c = invert_pose(ring_pose(3, 5, distance=3.0))[:3]
    rounded = w2c.copy()
    rounded[:, :3] *= 1 + 3e-5  # a pose stored with a few digits
    (src / "3-camera.pkl").write_bytes(pickle.dumps((rounded, GLOSSY_K)))
    scene = Scene.load(import_nero(src, tmp_path / "scene"))
    np.testing.assert_allclose(invert_pose(scene.frames[1].T_world_cam)[:3], w2c, atol=1e-6)  # (view 3)
    far = w2c.copy()
    far[:, 3] = 1e6
    (src / "3-camera.pkl").write_bytes(pickle.dumps((far, GLOSSY_K)))
    with pytest.raises(SceneFormatError, match="metres from the origin") as info:
        import_nero(src, tmp_path / "far")
    assert info.value.path == src / "3-camera.pkl" and info.value.field == "pose"


def test_a_copy_keeps_the_ground_truth_normals(tmp_path):
    """The benches copy an import before adding touches: its normal maps must come along for the normal error."""
    from tacsplat.datasets import copy_scene

    scene = Scene.load(import_blender(make_shiny_blender(tmp_path, 2, 2), tmp_path / "s", background_rgb=(0, 0, 0)))
    copy = Scene.load(copy_scene(scene, tmp_path / "copy"))
    test = scene.split("test")
    assert test and all(scene.gt_normal(f) is not None for f in test)
    for frame, copied in zip(scene.frames, copy.frames):
        normal = scene.gt_normal(frame)
        if normal is None:
            assert copy.gt_normal(copied) is None
        else:
            np.testing.assert_array_equal(copy.gt_normal(copied), normal)


def test_ground_truth_points_are_copied_and_a_damaged_file_is_named(tmp_path):
    from tacsplat.datasets import copy_scene

    scene = Scene.load(import_nero(make_glossy_synthetic(tmp_path), tmp_path / "scene"))
    copy = Scene.load(copy_scene(scene, tmp_path / "copy", frames=[scene.frames[0], scene.split("test")[1]]))
    assert len(copy.frames) == 2 and set(copy.gt_depth_files) == {1}
    np.testing.assert_array_equal(copy.gt_points(), scene.gt_points())
    (tmp_path / "copy" / "gt" / "points.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    with pytest.raises(SceneFormatError, match=r"points\.ply.*gt\.points"):
        Scene.load(tmp_path / "copy")
