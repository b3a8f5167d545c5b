"""SceneWriter -> Scene round trips, nerfstudio validity, undo, locking, scenes without touches."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import trimesh

from tacsplat.datasets import Scene, SceneMeta, SceneWriter, check_scene
from tacsplat.errors import InvalidInputError
from tacsplat.geometry import tactile_depth_to_points
from tacsplat.types import TactileReading


def test_everything_written_reads_back_exactly(tmp_path, h):
    path = h.build_scene(tmp_path / "s", n_frames=5, n_touches=6)
    scene = Scene.load(path)
    assert [f.id for f in scene.frames] == list(range(5))
    assert [f.split for f in scene.frames] == ["train", "test", "train", "train", "test"]
    assert [f.id for f in scene.split("test")] == [1, 4]
    for f in scene.frames:
        np.testing.assert_array_equal(f.T_world_cam, h.ring_pose(f.id))  # JSON floats round-trip exactly
        np.testing.assert_array_equal(f.intrinsics.K, h.intrinsics().K)
        np.testing.assert_array_equal(scene.load_image(f), h.frame_image(f.id).astype(np.float32) / 255)
        assert scene.load_image(f).dtype == np.float32
        gt = scene.gt_depth(f)
        if f.split == "test":
            np.testing.assert_array_equal(gt, np.full((h.HEIGHT, h.WIDTH), 0.4 + 0.01 * f.id, np.float32))
        else:
            assert gt is None
    assert scene.sensor == h.SENSOR
    assert scene.meta == SceneMeta(source="sim", object="test-object", capture_plan={"views": 5})
    assert [(t.id, t.grasp, t.finger, t.in_contact) for t in scene.touches] == [
        (i, i // 2, ["index", "thumb"][i % 2], i % 2 == 0) for i in range(6)
    ]
    assert scene.num_grasps == 3
    expected = np.concatenate(
        [tactile_depth_to_points(h.touch_depth(i), h.SENSOR.pixel_size_m, h.touch_pose(i)) for i in range(0, 6, 2)]
    )
    np.testing.assert_allclose(scene.touch_points(), expected)
    for t in scene.touches:
        np.testing.assert_array_equal(scene.load_touch_depth(t), h.touch_depth(t.id))
    meta = json.loads((path / "scene.json").read_text())
    assert meta["units"] == "m" and meta["source"] == "sim" and meta["tacsplat_version"]


def test_transforms_json_is_nerfstudio_input_with_opengl_matrices(scene_dir, h):
    data = json.loads((scene_dir / "transforms.json").read_text())
    assert data["camera_model"] == "OPENCV"
    intr = h.intrinsics()
    assert (data["fl_x"], data["fl_y"], data["cx"], data["cy"], data["w"], data["h"]) == (
        intr.fx,
        intr.fy,
        intr.cx,
        intr.cy,
        intr.width,
        intr.height,
    )
    for frame in data["frames"]:
        assert (scene_dir / frame["file_path"]).is_file()
        T = np.array(frame["transform_matrix"])
        assert T.shape == (4, 4) and np.array_equal(T[3], [0, 0, 0, 1])
        # OpenGL camera-to-world: the camera looks along its -z axis, here at the origin, with +y up-ish.
        view_dir = -T[:3, 2]
        to_origin = -T[:3, 3] / np.linalg.norm(T[:3, 3])
        assert view_dir @ to_origin > 0.999
        assert T[2, 1] > 0  # image-up (+y in OpenGL) points to world +z for these upright cameras
    names = {f["file_path"]: f["split"] for f in data["frames"]}
    assert data["train_filenames"] == [n for n, s in names.items() if s == "train"]
    assert data["test_filenames"] == data["val_filenames"] == [n for n, s in names.items() if s == "test"]


def test_per_frame_intrinsics_when_frames_differ(tmp_path, h):
    with SceneWriter.create(tmp_path / "s", h.intrinsics(), SceneMeta("real", "cup")) as w:
        w.add_frame(h.frame_image(0), h.ring_pose(0))
        other = h.intrinsics(width=20, height=10, f=9.0)
        w.add_frame(h.frame_image(1, 20, 10), h.ring_pose(1), intrinsics=other)
    data = json.loads((tmp_path / "s" / "transforms.json").read_text())
    assert "fl_x" not in data and "w" not in data  # nerfstudio then reads them from each frame
    assert [f["w"] for f in data["frames"]] == [16, 20]
    scene = Scene.load(tmp_path / "s")
    assert scene.intrinsics is None
    np.testing.assert_array_equal(scene.frames[1].intrinsics.K, other.K)


def test_scene_without_touches_or_sensor(tmp_path, h):
    path = h.build_scene(tmp_path / "s", n_frames=3, n_touches=0, sensor=None)
    assert json.loads((path / "touches.json").read_text()) == {"sensor": None, "touches": []}
    scene = Scene.load(path)
    assert scene.sensor is None and scene.touches == [] and scene.num_grasps == 0
    assert scene.touch_points().shape == (0, 3)
    lo, hi = scene.bounds()
    assert np.all(lo < 0) and np.all(hi > 0)  # the cameras look at the origin
    with SceneWriter.resume(path) as w:
        with pytest.raises(InvalidInputError, match="without a sensor model"):
            w.add_touch(np.zeros((8, 10), np.float32), np.eye(4), grasp=0, finger="index")


def test_bounds_hold_the_region_every_camera_sees_and_the_touches(scene_dir):
    scene = Scene.load(scene_dir)
    lo, hi = scene.bounds()
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=0.02)  # the cameras' axes meet at the origin
    points = scene.touch_points()
    assert np.all(points >= lo) and np.all(points <= hi)
    for f in scene.frames:  # the box's centre projects inside every image
        from tacsplat.geometry import project_points

        uv, z = project_points(((lo + hi) / 2)[None], f.intrinsics.K, f.T_world_cam)
        assert z[0] > 0 and 0 <= uv[0, 0] <= f.intrinsics.width and 0 <= uv[0, 1] <= f.intrinsics.height


def test_remove_last_undoes_in_order_and_ids_are_reused(tmp_path, h):
    path = tmp_path / "s"
    with SceneWriter.create(path, h.intrinsics(), SceneMeta("real", "cup"), h.SENSOR) as w:
        w.add_frame(h.frame_image(0), h.ring_pose(0))
        w.add_touch(h.touch_depth(0), h.touch_pose(0), grasp=0, finger="index")
        f1 = w.add_frame(
            h.frame_image(1), h.ring_pose(1), split="test", gt_depth=np.ones((h.HEIGHT, h.WIDTH), np.float32)
        )
        assert w.remove_last() == f1
        assert not (path / f1.file_path).exists() and not (path / "gt/depth/000001.npz").exists()
        removed = w.remove_last()
        assert removed.id == 0 and removed.finger == "index"
        assert (w.num_frames, w.num_touches) == (1, 0)
        again = w.add_frame(h.frame_image(5), h.ring_pose(5))
        assert again.id == 1
    scene = Scene.load(path)
    assert [f.id for f in scene.frames] == [0, 1] and scene.touches == [] and scene.gt_depth_files == {}
    np.testing.assert_array_equal(scene.load_image(scene.frames[1]), h.frame_image(5) / np.float32(255))
    with SceneWriter.resume(path) as w:  # the journal replays the undos
        assert (w.num_frames, w.num_touches) == (2, 0)
        w.remove_last()
        with pytest.raises(InvalidInputError, match="nothing to remove"):
            w.remove_last(), w.remove_last()


def test_gt_mesh_and_world_frame_readings(tmp_path, h):
    path = tmp_path / "s"
    with SceneWriter.create(path, h.intrinsics(), SceneMeta("sim", "box"), h.SENSOR) as w:
        w.add_frame(h.frame_image(0), h.ring_pose(0))
        w.set_gt_mesh(trimesh.creation.box(extents=(0.1, 0.2, 0.3)))
        reading = TactileReading(depth=h.touch_depth(0), pixel_size_m=h.SENSOR.pixel_size_m, T_ref_sensor=np.eye(4))
        with pytest.raises(InvalidInputError, match="to_world"):
            w.add_reading(reading, grasp=0, finger="index")
        touch = w.add_reading(reading.to_world(h.touch_pose(0)), grasp=0, finger="index")
        np.testing.assert_allclose(touch.T_world_sensor, h.touch_pose(0))
    scene = Scene.load(path)
    mesh = trimesh.load(scene.gt_mesh_path)
    np.testing.assert_allclose(mesh.extents, [0.1, 0.2, 0.3])


def test_writer_rejects_bad_arguments_naming_them(tmp_path, h):
    with SceneWriter.create(tmp_path / "s", h.intrinsics(), SceneMeta("sim", "x"), h.SENSOR) as w:
        bad_pose = h.ring_pose(0).copy()
        bad_pose[:3, :3] *= 1.01
        far_pose = h.ring_pose(0).copy()
        far_pose[:3, 3] = [2e5, 0.0, 0.0]
        cases = [
            (lambda: w.add_frame(h.frame_image(0), bad_pose), "T_world_cam: not a rigid"),
            (lambda: w.add_frame(h.frame_image(0)[:5], h.ring_pose(0)), r"image: expected uint8 RGB \(12, 16, 3\)"),
            (lambda: w.add_frame(h.frame_image(0).astype(np.float32), h.ring_pose(0)), "image: expected uint8"),
            (lambda: w.add_frame(h.frame_image(0), h.ring_pose(0), split="val"), "split"),
            (
                lambda: w.add_frame(h.frame_image(0), h.ring_pose(0), gt_depth=np.full((12, 16), np.nan, np.float32)),
                "gt_depth: 192 non-finite",
            ),
            (lambda: w.add_touch(-h.touch_depth(0), h.touch_pose(0), 0, "index"), "depth: negative depth values"),
            (lambda: w.add_touch(h.touch_depth(0) * 1e3, h.touch_pose(0), 0, "index"), "deeper than 10 x the gel"),
            (lambda: w.add_frame(h.frame_image(0), far_pose), "T_world_cam: its origin is 2e\\+05 metres"),
            (lambda: w.add_frame(h.frame_image(0), h.ring_pose(0), intrinsics=h.intrinsics(f=1e8)), "intrinsics.fl_x"),
            (lambda: w.add_touch(np.zeros((3, 3), np.float32), h.touch_pose(0), 0, "index"), "depth: expected shape"),
            (lambda: w.add_touch(h.touch_depth(0), h.touch_pose(0), -1, "index"), "grasp"),
        ]
        for call, message in cases:
            with pytest.raises(InvalidInputError, match=message):
                call()
        assert (w.num_frames, w.num_touches) == (0, 0)  # nothing half-written
    scene, problems = check_scene(tmp_path / "s")
    assert scene.frames == [] and [p.field for p in problems] == ["frames"]  # only: the scene has no frames


def test_create_rejects_metadata_that_is_not_json(tmp_path, h):
    with pytest.raises(InvalidInputError, match="capture_plan and extra must be plain JSON"):
        SceneWriter.create(tmp_path / "s", h.intrinsics(), SceneMeta("sim", "x", capture_plan={"pose": np.eye(4)}))
    assert not (tmp_path / "s").exists()


def test_one_writer_at_a_time_and_no_overwrite(scene_dir, h):
    with SceneWriter.resume(scene_dir):
        with pytest.raises(
            InvalidInputError,
            match=rf"being written by another tacsplat process \(PID {os.getpid()}\)"
            ".* --resume",
        ):
            SceneWriter.resume(scene_dir)
        with pytest.raises(InvalidInputError, match="being written by another tacsplat process"):
            SceneWriter.create(scene_dir, h.intrinsics(), SceneMeta("sim", "x"))
    with pytest.raises(InvalidInputError, match="already holds a scene: continue it with --resume"):
        SceneWriter.create(scene_dir, h.intrinsics(), SceneMeta("sim", "x"))
    SceneWriter.resume(scene_dir).close()  # the lock is released on close


def _masks(i: int, h) -> np.ndarray:
    mask = np.zeros((h.HEIGHT, h.WIDTH), bool)
    mask[2 : 6 + i, 3:12] = True
    return mask


def test_masks_are_written_read_back_and_exported_for_nerfstudio(tmp_path, h):
    path = tmp_path / "s"
    with SceneWriter.create(path, h.intrinsics(), SceneMeta("real", "cup")) as w:
        for i in range(3):
            w.add_frame(h.frame_image(i), h.ring_pose(i), split="test" if i == 1 else "train", mask=_masks(i, h))
        with pytest.raises(InvalidInputError, match="mask: expected bool"):
            w.add_frame(h.frame_image(3), h.ring_pose(3), mask=_masks(0, h).astype(np.uint8))
        with pytest.raises(InvalidInputError, match="masks on every frame or on none"):
            w.add_frame(h.frame_image(3), h.ring_pose(3))
        last = w.remove_last()
        assert not (path / last.mask_path).exists()  # the undo takes the mask with it
        w.add_frame(h.frame_image(2), h.ring_pose(2), mask=_masks(2, h))
    scene = Scene.load(path)
    assert [f.mask_path for f in scene.frames] == ["masks/000000.png", "masks/000001.png", "masks/000002.png"]
    for f in scene.frames:
        np.testing.assert_array_equal(scene.load_mask(f), _masks(f.id, h))
    data = json.loads((path / "transforms.json").read_text())
    assert [f["mask_path"] for f in data["frames"]] == ["masks/000000.png", "masks/000001.png", "masks/000002.png"]
    with SceneWriter.resume(path) as w:  # the journal keeps them
        assert [f.mask_path for f in w.frames] == [f.mask_path for f in scene.frames]
    unmasked = h.build_scene(tmp_path / "plain", n_frames=2, n_touches=0, sensor=None)
    assert Scene.load(unmasked).load_mask(Scene.load(unmasked).frames[0]) is None
    with SceneWriter.resume(unmasked) as w, pytest.raises(InvalidInputError, match="frame 0 has none"):
        w.add_frame(h.frame_image(2), h.ring_pose(2), mask=_masks(0, h))


def test_an_orphan_mask_of_a_crashed_record_is_removed_on_resume(tmp_path, h):
    path = tmp_path / "s"
    with SceneWriter.create(path, h.intrinsics(), SceneMeta("real", "cup")) as w:
        w.add_frame(h.frame_image(0), h.ring_pose(0), mask=_masks(0, h))
    (path / "masks/000001.png").write_bytes((path / "masks/000000.png").read_bytes())  # written, never journaled
    SceneWriter.resume(path).close()
    assert sorted(p.name for p in (path / "masks").iterdir()) == ["000000.png"]
