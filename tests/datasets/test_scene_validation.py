"""Every kind of bad scene input raises one SceneFormatError naming the file and field at fault."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from PIL import Image

from tacsplat.datasets import Scene, check_scene
from tacsplat.errors import SceneFormatError


def _edit_json(path, edit):
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def _transforms(edit):
    return lambda s: _edit_json(s / "transforms.json", edit)


def _touches(edit):
    return lambda s: _edit_json(s / "touches.json", edit)


def _scale_rotation(T, factor):
    T = np.array(T)
    T[:3, :3] *= factor
    return T.tolist()


def _reflect(T):
    T = np.array(T)
    T[:3, 0] *= -1
    return T.tolist()


def _save_npz(path, depth):
    buf = io.BytesIO()
    np.savez(buf, depth=depth)
    path.write_bytes(buf.getvalue())


def _truncate(path, keep=0.5):
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def _masks_on_frames(*ids, size=(12, 16), channels=1):
    """Give frames ``ids`` a mask file and a mask_path."""

    def corrupt(s):
        (s / "masks").mkdir()
        for i in ids:
            shape = size if channels == 1 else (*size, channels)
            Image.fromarray(np.full(shape, 255, np.uint8)).save(s / f"masks/{i:06d}.png")
        _edit_json(
            s / "transforms.json",
            lambda d: [f.update(mask_path=f"masks/{f['id']:06d}.png") for f in d["frames"] if f["id"] in ids],
        )

    return corrupt


def _nan_patch(shape):
    d = np.zeros(shape, np.float32)
    d[1, 1] = np.nan
    return d


# (corruption, file the error names, field the error names, words of the message)
CASES = {
    "missing image": (
        lambda s: (s / "images/000002.png").unlink(),
        "transforms.json",
        "frames[2].file_path",
        "missing",
    ),
    "corrupt image": (
        lambda s: (s / "images/000001.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20),
        "000001.png",
        "frames[1].file_path",
        "corrupt",
    ),
    "truncated image": (
        lambda s: _truncate(s / "images/000003.png"),
        "000003.png",
        "frames[3].file_path",
        "corrupt or truncated",
    ),
    "image size vs w, h": (
        _transforms(lambda d: d.update(w=17)),
        "000000.png",
        "frames[0].file_path",
        "image is 16x12 but the camera says w x h = 17x12",
    ),
    "truncated touch npz": (
        lambda s: _truncate(s / "touches/000001.npz"),
        "000001.npz",
        "touch 1 depth",
        "truncated or corrupt npz",
    ),
    "non-finite touch depth": (
        lambda s: _save_npz(s / "touches/000002.npz", _nan_patch((8, 10))),
        "000002.npz",
        "touch 2 depth",
        "non-finite",
    ),
    "negative touch depth": (
        lambda s: _save_npz(s / "touches/000000.npz", -np.ones((8, 10), np.float32)),
        "000000.npz",
        "touch 0 depth",
        "negative depth",
    ),
    "touch depth vs sensor model": (
        _touches(lambda d: d["sensor"].update(width_px=11)),
        "000000.npz",
        "touch 0 depth",
        "does not match the expected (8, 11)",
    ),
    "non-finite gt depth": (
        lambda s: _save_npz(s / "gt/depth/000001.npz", _nan_patch((12, 16))),
        "000001.npz",
        "gt depth of frame 1",
        "non-finite",
    ),
    "gt depth vs image size": (
        lambda s: _save_npz(s / "gt/depth/000001.npz", np.ones((12, 15), np.float32)),
        "000001.npz",
        "gt depth of frame 1",
        "does not match the expected (12, 16)",
    ),
    "frame pose not orthonormal": (
        _transforms(
            lambda d: d["frames"][1].update(transform_matrix=_scale_rotation(d["frames"][1]["transform_matrix"], 1.1))
        ),
        "transforms.json",
        "frames[1].transform_matrix",
        "not orthonormal",
    ),
    "frame pose is a reflection": (
        _transforms(lambda d: d["frames"][2].update(transform_matrix=_reflect(d["frames"][2]["transform_matrix"]))),
        "transforms.json",
        "frames[2].transform_matrix",
        "determinant is -1",
    ),
    "frame pose not 4x4": (
        _transforms(lambda d: d["frames"][0].update(transform_matrix=[[1, 0, 0], [0, 1, 0]])),
        "transforms.json",
        "frames[0].transform_matrix",
        "expected a 4x4 matrix",
    ),
    "touch pose not rigid": (
        _touches(
            lambda d: d["touches"][3].update(T_world_sensor=_scale_rotation(d["touches"][3]["T_world_sensor"], 0.5))
        ),
        "touches.json",
        "touches[3].T_world_sensor",
        "not orthonormal",
    ),
    "unknown split": (
        _transforms(lambda d: d["frames"][3].update(split="val")),
        "transforms.json",
        "frames[3].split",
        "unknown split 'val'",
    ),
    "duplicate frame id": (
        _transforms(lambda d: d["frames"][2].update(id=0)),
        "transforms.json",
        "frames[2].id",
        "duplicate frame id 0",
    ),
    "duplicate touch id": (
        _touches(lambda d: d["touches"][3].update(id=1)),
        "touches.json",
        "touches[3].id",
        "duplicate touch id 1",
    ),
    "in_contact contradicts the depth": (
        _touches(lambda d: d["touches"][1].update(in_contact=True)),
        "touches.json",
        "touches[1].in_contact",
        "says True",
    ),
    "missing transforms.json": (lambda s: (s / "transforms.json").unlink(), "transforms.json", None, "missing"),
    "corrupt scene.json": (
        lambda s: (s / "scene.json").write_text('{"source": '),
        "scene.json",
        None,
        "not valid JSON",
    ),
    "wrong units": (
        lambda s: _edit_json(s / "scene.json", lambda d: d.update(units="mm")),
        "scene.json",
        "units",
        "'m'",
    ),
    # the index behind its journal: what inspect rejects, every reader rejects
    "touches.json deleted": (
        lambda s: (s / "touches.json").unlink(),
        "journal.jsonl",
        None,
        "records 4 frames and 4 touches but the index files hold 4 and 0",
    ),
    "a touch dropped from the index": (
        _touches(lambda d: d["touches"].pop(1)),
        "journal.jsonl",
        None,
        "the index files hold 4 and 3",
    ),
    "a frame dropped from the index": (
        _transforms(lambda d: d["frames"].pop()),
        "journal.jsonl",
        None,
        "the index files hold 3 and 4",
    ),
    "only test frames": (
        _transforms(lambda d: [f.update(split="test") for f in d["frames"]]),
        "transforms.json",
        "frames",
        "no train frames",
    ),
    # numbers that no camera, sensor or capture can have
    "JSON NaN focal length": (
        _transforms(lambda d: d.update(fl_x=float("nan"))),
        "transforms.json",
        "frames[0].fl_x",
        "expected a finite positive number, got nan",
    ),
    "focal length of a telescope": (
        _transforms(lambda d: d.update(fl_y=1e9)),
        "transforms.json",
        "frames[0].fl_y",
        "field of view",
    ),
    "focal length of a fisheye": (
        _transforms(lambda d: d.update(fl_x=0.5)),
        "transforms.json",
        "frames[0].fl_x",
        "field of view",
    ),
    "principal point outside the image": (
        _transforms(lambda d: d.update(cx=-3.0)),
        "transforms.json",
        "frames[0].cx",
        "inside the image, 0..16",
    ),
    "zero image width": (_transforms(lambda d: d.update(w=0)), "transforms.json", "frames[0].w", "positive integer"),
    "absurd image height": (
        _transforms(lambda d: d.update(h=10**400)),
        "transforms.json",
        "frames[0].h",
        "positive integer up to 65536",
    ),
    "width that is a boolean": (
        _transforms(lambda d: d.update(w=True)),
        "transforms.json",
        "frames[0].w",
        "positive integer",
    ),
    "camera at the far end of the universe": (
        _transforms(lambda d: d["frames"][1]["transform_matrix"][0].__setitem__(3, 1e12)),
        "transforms.json",
        "frames[1].transform_matrix",
        "metres from the origin",
    ),
    "pose entry too big for a float": (
        _transforms(lambda d: d["frames"][1]["transform_matrix"][2].__setitem__(3, 10**400)),
        "transforms.json",
        "frames[1].transform_matrix",
        "4x4 matrix of numbers",
    ),
    "JSON infinity in a touch pose": (
        _touches(lambda d: d["touches"][2]["T_world_sensor"][1].__setitem__(3, float("inf"))),
        "touches.json",
        "touches[2].T_world_sensor",
        "NaN or infinite",
    ),
    "zero gel thickness": (
        _touches(lambda d: d["sensor"].update(gel_thickness_m=0.0)),
        "touches.json",
        "sensor",
        "gel_thickness_m must be positive",
    ),
    "negative pixel size": (
        _touches(lambda d: d["sensor"].update(pixel_size_m=-5e-4)),
        "touches.json",
        "sensor",
        "pixel_size_m must be positive",
    ),
    "pixel size in light years": (
        _touches(lambda d: d["sensor"].update(pixel_size_m=1e16)),
        "touches.json",
        "sensor",
        "pixel_size_m",
    ),
    "sensor name that is not a name": (
        _touches(lambda d: d["sensor"].update(name=7)),
        "touches.json",
        "sensor",
        "name must be a non-empty string",
    ),
    "indentation far deeper than the gel": (
        lambda s: _save_npz(s / "touches/000000.npz", np.full((8, 10), 0.5, np.float32)),
        "000000.npz",
        "touch 0 depth",
        "10 x the gel thickness",
    ),
    "integer touch depth": (
        lambda s: _save_npz(s / "touches/000002.npz", np.ones((8, 10), np.int32)),
        "000002.npz",
        "touch 2 depth",
        "expected float metres",
    ),
    "gt depth beyond any scene": (
        lambda s: _save_npz(s / "gt/depth/000001.npz", np.full((12, 16), 1e30, np.float32)),
        "000001.npz",
        "gt depth of frame 1",
        "deeper than any scene",
    ),
    "gt depth key a digit but no number": (  # "²".isdigit() is True, int("²") fails
        lambda s: _edit_json(
            s / "scene.json", lambda d: d["gt"]["depth"].update({"\u00b2": d["gt"]["depth"].pop("1")})
        ),
        "scene.json",
        "gt.depth[\u00b2]",
        "no frame with id '\u00b2'",
    ),
    "unknown scene format version": (
        lambda s: _edit_json(s / "scene.json", lambda d: d.update(format_version="1")),
        "scene.json",
        "format_version",
        "expected 1",
    ),
    "image width that is not whole": (
        _transforms(lambda d: d.update(w=16.5)),
        "transforms.json",
        "frames[0].w",
        "positive integer up to 65536 (1080 or 1080.0), got 16.5",
    ),
    # what nerfstudio writes and a scene never holds: refused rather than silently ignored
    "nerfstudio's applied_transform": (
        _transforms(lambda d: d.update(applied_transform=[[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0]])),
        "transforms.json",
        "applied_transform",
        "tacsplat import nerfstudio",
    ),
    "a frame's depth_file_path": (
        _transforms(lambda d: d["frames"][2].update(depth_file_path="depths/x.png")),
        "transforms.json",
        "frames[2].depth_file_path",
        "not part of a tacsplat scene",
    ),
    "missing mask": (
        _transforms(lambda d: [f.update(mask_path=f"masks/{f['id']:06d}.png") for f in d["frames"]]),
        "transforms.json",
        "frames[0].mask_path",
        "mask file 000000.png is missing",
    ),
    "mask on some frames only": (_masks_on_frames(0, 3), "transforms.json", "frames", "2 of 4 frames have a mask_path"),
    "mask of another size": (
        _masks_on_frames(0, 1, 2, 3, size=(12, 15)),
        "000000.png",
        "frames[0].mask_path",
        "image is 15x12 but the camera says w x h = 16x12",
    ),
    "a frame's own distortion": (  # nerfstudio reads a frame's camera keys over the top-level ones
        _transforms(lambda d: d["frames"][1].update(k1=0.3, p1=0.01)),
        "transforms.json",
        "frames[1].k1",
        "images must be undistorted, but k1 = 0.3",
    ),
    "a frame's own distorted camera model": (
        _transforms(lambda d: d["frames"][0].update(camera_model="OPENCV_FISHEYE")),
        "transforms.json",
        "frames[0].camera_model",
        "expected OPENCV or PINHOLE (undistorted images), got 'OPENCV_FISHEYE'",
    ),
    "mask in colour": (
        _masks_on_frames(0, 1, 2, 3, channels=3),
        "000000.png",
        "frames[0].mask_path",
        "expected an 8-bit greyscale mask, got PIL mode 'RGB'",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_raises_one_error_naming_file_and_field(scene_dir, case):
    corrupt, filename, field, words = CASES[case]
    corrupt(scene_dir)
    with pytest.raises(SceneFormatError) as info:
        Scene.load(scene_dir)
    err = info.value
    assert err.path.name == filename, str(err)
    assert err.field == field, str(err)
    assert words in str(err)
    assert str(err).startswith(str(err.path))


def test_check_scene_collects_every_problem_and_keeps_the_rest(scene_dir):
    CASES["missing image"][0](scene_dir)
    CASES["unknown split"][0](scene_dir)
    CASES["truncated touch npz"][0](scene_dir)
    scene, problems = check_scene(scene_dir)
    assert sorted(p.field for p in problems) == ["frames[2].file_path", "frames[3].split", "touch 1 depth"]
    assert [f.id for f in scene.frames] == [0, 1, 2]  # frame 2's record is sound: kept, its missing image a problem
    assert [t.id for t in scene.touches] == [0, 2, 3]


def test_valid_scene_has_no_problems(scene_dir):
    assert check_scene(scene_dir)[1] == []


def test_a_scene_without_frames_is_invalid(tmp_path, h):
    path = h.build_scene(tmp_path / "s", n_frames=0, n_touches=2)
    with pytest.raises(SceneFormatError, match="no frames") as info:
        Scene.load(path)
    assert info.value.path == path / "transforms.json" and info.value.field == "frames"
    assert [str(p) for p in check_scene(path)[1]] == [str(info.value)]


def test_whole_float_image_sizes_are_read_as_instant_ngp_writes_them(scene_dir):
    _edit_json(scene_dir / "transforms.json", lambda d: d.update(w=16.0, h=12.0))
    scene = Scene.load(scene_dir)
    assert {(f.intrinsics.width, f.intrinsics.height) for f in scene.frames} == {(16, 12)}
    assert all(isinstance(f.intrinsics.width, int) for f in scene.frames)


def test_a_scene_with_masks_on_every_frame_is_valid(scene_dir):
    _masks_on_frames(0, 1, 2, 3)(scene_dir)
    scene = Scene.load(scene_dir)
    assert all(scene.load_mask(f).all() for f in scene.frames)
