"""copy_scene: a new scene through SceneWriter with every frame, a chosen subset of touches, new provenance or
sensor model; a failed copy leaves no folder behind."""

import numpy as np
import pytest
import trimesh

from tacsplat.datasets import Scene, SceneMeta, SceneWriter, SensorModel, check_scene, copy_scene
from tacsplat.errors import InvalidInputError


def _frames(scene: Scene) -> list:
    return [
        (
            f.split,
            f.T_world_cam.tobytes(),
            f.intrinsics.K.tobytes(),
            scene.load_image(f).tobytes(),
            None if scene.gt_depth(f) is None else scene.gt_depth(f).tobytes(),
        )
        for f in scene.frames
    ]


def test_a_copy_keeps_every_frame_and_the_chosen_touches_in_order(scene_dir, tmp_path):
    with SceneWriter.resume(scene_dir) as writer:
        writer.set_gt_mesh(trimesh.creation.icosphere(subdivisions=1, radius=0.05))
    source = Scene.load(scene_dir)
    kept = [source.touches[2], source.touches[0]]
    meta = SceneMeta(source="sim", object="test-object", extra={"subsample": 2})
    out = copy_scene(scene_dir, tmp_path / "copy", touches=kept, meta=meta)
    copy, problems = check_scene(out)
    assert problems == []
    assert _frames(copy) == _frames(source)
    assert copy.meta == meta and copy.sensor == source.sensor
    assert [(t.id, t.grasp, t.finger) for t in copy.touches] == [(0, 1, "index"), (1, 0, "index")]
    for new, old in zip(copy.touches, kept):
        assert np.array_equal(new.T_world_sensor, old.T_world_sensor)
        assert np.array_equal(copy.load_touch_depth(new), source.load_touch_depth(old))
    assert copy.gt_mesh_path.read_bytes() == source.gt_mesh_path.read_bytes()


def test_by_default_everything_is_copied(scene_dir, tmp_path):
    source = Scene.load(scene_dir)
    copy = Scene.load(copy_scene(source, tmp_path / "copy"))
    assert _frames(copy) == _frames(source) and copy.meta == source.meta
    assert [(t.grasp, t.finger, t.in_contact) for t in copy.touches] == [
        (t.grasp, t.finger, t.in_contact) for t in source.touches
    ]


def test_a_new_sensor_model_only_without_touches(scene_dir, tmp_path):
    other = SensorModel(name="sim-digit", width_px=20, height_px=16, pixel_size_m=1e-4, gel_thickness_m=2e-3)
    with pytest.raises(InvalidInputError, match="sensor"):
        copy_scene(scene_dir, tmp_path / "refused", sensor=other)
    assert not (tmp_path / "refused").exists()
    copy = Scene.load(copy_scene(scene_dir, tmp_path / "copy", touches=[], sensor=other))
    assert copy.sensor == other and copy.touches == []


def test_a_touch_of_another_scene_is_refused_and_nothing_is_left(scene_dir, tmp_path, h):
    elsewhere = Scene.load(h.build_scene(tmp_path / "elsewhere", n_touches=6))
    with pytest.raises(InvalidInputError, match="not a touch of"):
        copy_scene(scene_dir, tmp_path / "copy", touches=[elsewhere.touches[5]])
    assert not (tmp_path / "copy").exists()


def test_a_copy_failing_midway_removes_its_folder(scene_dir, tmp_path, monkeypatch):
    def broken(self, touch):
        raise OSError("disk unplugged")

    monkeypatch.setattr(Scene, "load_touch_depth", broken)
    with pytest.raises(OSError, match="unplugged"):
        copy_scene(scene_dir, tmp_path / "copy")
    assert not (tmp_path / "copy").exists()


def test_an_existing_scene_is_never_overwritten(scene_dir, tmp_path, h):
    target = h.build_scene(tmp_path / "target")
    before = {p: p.read_bytes() for p in target.rglob("*") if p.is_file()}
    with pytest.raises(InvalidInputError, match="already holds a scene"):
        copy_scene(scene_dir, target)
    assert {p: p.read_bytes() for p in target.rglob("*") if p.is_file()} == before
