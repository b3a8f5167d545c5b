"""Importers refuse wrong geometry with one error naming the file and the line, entry or field: COLMAP models
(text and binary, with and without rigs and frames), nerfstudio distortion and splits, Blender EXR frames."""

from __future__ import annotations

import json
import logging
import struct
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from tacsplat.cli import main
from tacsplat.datasets import Scene
from tacsplat.datasets.colmap import import_colmap
from tacsplat.datasets.nerfstudio import import_nerfstudio
from tacsplat.errors import SceneFormatError
from tacsplat.geometry import invert_pose, look_at, opencv_to_opengl

W, H = 10, 8


def _posed_image(iid: int, camera_id: int, name: str) -> tuple[pycolmap.Image, pycolmap.Rigid3d]:
    T_world_cam = look_at([np.cos(iid), np.sin(iid), 0.3 * iid], [0.1, 0.0, 0.0])
    points = pycolmap.Point2DList([pycolmap.Point2D(np.array([1.0 + k, 2.0])) for k in range(3)])
    return (
        pycolmap.Image(name=name, camera_id=camera_id, image_id=iid, points2D=points),
        pycolmap.Rigid3d(invert_pose(T_world_cam)[:3, :4]),
    )


@pytest.fixture(params=["text", "binary", "text-legacy", "binary-legacy"])
def colmap_model(request, tmp_path):
    """Three images of one PINHOLE camera, one 3D point seen by images 1 (2D point 0) and 2 (2D point 1); as
    COLMAP >= 3.12 writes it (with rigs and frames) or older COLMAP (without). Returns (model dir, images dir)."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[9.0, 9.5, 5.2, 3.9], camera_id=1)
    )
    images = tmp_path / "images"
    images.mkdir()
    for iid in (1, 2, 3):
        rec.add_image_with_trivial_frame(*_posed_image(iid, 1, f"img_{iid:02d}.png"))
        cv2.imwrite(str(images / f"img_{iid:02d}.png"), np.full((H, W, 3), 40 * iid, np.uint8))
    track = pycolmap.Track()
    track.add_element(1, 0)
    track.add_element(2, 1)
    rec.add_point3D(np.array([0.1, 0.2, 0.3]), track, np.array([10, 20, 30], np.uint8))
    kind = request.param.split("-")[0]
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    getattr(rec, f"write_{kind}")(str(model))
    if request.param.endswith("legacy"):
        for name in ("rigs", "frames"):
            next(model.glob(f"{name}.*")).unlink()
    return model, images


def _text_field(path: Path, line: int, index: int, value: str) -> None:
    lines = path.read_text().split("\n")
    fields = lines[line - 1].split()
    fields[index] = value
    lines[line - 1] = " ".join(fields)
    path.write_text("\n".join(lines))


def _pack(path: Path, offset, fmt: str, value) -> None:
    """Overwrite one value of a binary model file; ``offset`` may be a function of the file's bytes."""
    data = bytearray(path.read_bytes())
    struct.pack_into("<" + fmt, data, offset(data) if callable(offset) else offset, value)
    path.write_bytes(bytes(data))


def _name_at(name: str):
    return lambda data: data.find(name.encode() + b"\0")


def _after_name(name: str, delta: int):
    return lambda data: data.find(name.encode() + b"\0") + delta


# In the text files: cameras.txt line 4 is camera 1; images.txt lines 5, 7, 9 are images 1-3 (their POINTS2D on
# the line after); points3D.txt line 4 is point 1 (ID X Y Z R G B ERROR 1 0 2 1); frames.txt line 4 is frame 1.
# In the binary files (COLMAP's layout): images.bin holds ID, QW..TZ, CAMERA_ID before each name and the number of
# 2D points and (X, Y, POINT3D_ID) after it; points3D.bin holds (IMAGE_ID, POINT2D_IDX) pairs from byte 59;
# cameras.bin holds camera 1's model id at byte 12 and fx at byte 32; frames.bin frame 1's rig id at byte 12.
CASES = {
    "a repeated NAME": (
        lambda m: _text_field(m / "images.txt", 7, 9, "img_01.png"),
        lambda m: _pack(m / "images.bin", _name_at("img_02.png"), "10s", b"img_01.png"),
        "images",
        2,
        ("NAME img_01.png again", "image 2", "image 1"),
    ),
    "a camera id cameras lacks": (
        lambda m: _text_field(m / "images.txt", 7, 8, "7"),
        lambda m: _pack(m / "images.bin", _after_name("img_02.png", -4), "I", 7),
        "images",
        2,
        ("image 2 names camera 7",),
    ),
    "a track naming a missing 2D point": (
        lambda m: _text_field(m / "points3D.txt", 4, 11, "9"),
        lambda m: _pack(m / "points3D.bin", 71, "I", 9),
        "points3D",
        1,
        ("point 1", "POINT2D_IDX 9 of image 2", "3 2D points"),
    ),
    "a track naming a missing image": (
        lambda m: _text_field(m / "points3D.txt", 4, 10, "42"),
        lambda m: _pack(m / "points3D.bin", 67, "I", 42),
        "points3D",
        1,
        ("point 1", "image 42"),
    ),
    "a 2D point naming a missing 3D point": (
        lambda m: _text_field(m / "images.txt", 6, 2, "5"),
        lambda m: _pack(m / "images.bin", _after_name("img_01.png", 11 + 8 + 16), "q", 5),
        "images",
        1,
        ("POINTS2D[0] of image 1", "3D point 5"),
    ),
    "a POINT3D_ID beyond int64": (
        lambda m: _text_field(m / "points3D.txt", 4, 0, str(2**63)),
        lambda m: _pack(m / "points3D.bin", 8, "Q", 2**63),
        "points3D",
        1,
        ("POINT3D_ID must be an integer from 0 to", str(2**63)),
    ),
    "a NaN in a pose": (
        lambda m: _text_field(m / "images.txt", 7, 1, "nan"),
        lambda m: _pack(m / "images.bin", _after_name("img_02.png", -60), "d", float("nan")),
        "images",
        2,
        ("image 2's pose is not finite",),
    ),
    "a quaternion that is no rotation": (
        lambda m: _text_field(m / "images.txt", 7, 2, "0.9"),
        lambda m: _pack(m / "images.bin", _after_name("img_02.png", -52), "d", 0.9),
        "images",
        2,
        ("image 2's pose", "not 1"),
    ),
    "a negative focal length": (
        lambda m: _text_field(m / "cameras.txt", 4, 4, "-9"),
        lambda m: _pack(m / "cameras.bin", 32, "d", -9.0),
        "cameras",
        1,
        ("camera 1", "focal length", "-9"),
    ),
    "an unknown camera model": (
        lambda m: _text_field(m / "cameras.txt", 4, 1, "FOOBAR"),
        lambda m: _pack(m / "cameras.bin", 12, "i", 99),
        "cameras",
        1,
        ("camera 1", "unknown camera model"),
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_broken_colmap_model_is_one_error_naming_the_file_and_line_or_entry(colmap_model, case, tmp_path):
    model, images = colmap_model
    edit_text, edit_binary, name, entry, words = CASES[case]
    binary = (model / "images.bin").exists()
    (edit_binary if binary else edit_text)(model)
    with pytest.raises(SceneFormatError) as info:
        import_colmap(model, images, tmp_path / "scene")
    line = {"cameras": 3, "images": 3 + 2 * entry, "points3D": 3}[name] + (0 if name == "images" else entry)
    assert info.value.path == model / f"{name}.{'bin' if binary else 'txt'}"
    assert info.value.field == (f"entry {entry}" if binary else f"line {line}")
    for word in words:
        assert word in str(info.value), str(info.value)
    assert not (tmp_path / "scene").exists()


@pytest.mark.parametrize("colmap_model", ["text", "text-legacy"], indirect=True)
@pytest.mark.parametrize(
    "field, value, words",
    [
        (0, "99999999999999999999999", "IMAGE_ID must be an integer from 0 to 4294967295"),  # beyond int64
        (0, "4294967296", "IMAGE_ID must be an integer from 0 to 4294967295"),  # beyond COLMAP's image_t
        (8, "-1", "CAMERA_ID must be an integer from 0 to 4294967295"),
    ],
)
def test_a_text_id_no_binary_model_can_hold_names_the_line(colmap_model, tmp_path, field, value, words):
    model, images = colmap_model
    _text_field(model / "images.txt", 7, field, value)
    with pytest.raises(SceneFormatError, match=words) as info:
        import_colmap(model, images, tmp_path / "scene")
    assert info.value.path == model / "images.txt" and info.value.field == "line 7"
    assert not (tmp_path / "scene").exists()


@pytest.mark.parametrize("case", ["a repeated NAME", "a camera id cameras lacks", "a track naming a missing 2D point"])
def test_the_issues_cases_are_one_error_line_from_the_cli(colmap_model, case, tmp_path, capsys):
    model, images = colmap_model
    edit_text, edit_binary, name, *_ = CASES[case]
    binary = (model / "images.bin").exists()
    (edit_binary if binary else edit_text)(model)
    assert main(["import", "colmap", str(model), "--images", str(images), "--out", str(tmp_path / "scene")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and "Traceback" not in err, err
    assert f"{name}.{'bin' if binary else 'txt'} [" in err


def test_a_missing_picture_names_the_image_entry_and_the_images_option(colmap_model, tmp_path):
    model, images = colmap_model
    (images / "img_02.png").unlink()
    with pytest.raises(SceneFormatError, match="img_02.png does not exist.*--images") as info:
        import_colmap(model, images, tmp_path / "scene")
    assert info.value.path.stem == "images" and info.value.field in ("line 7", "entry 2")


@pytest.mark.parametrize("colmap_model", ["text", "binary"], indirect=True)
def test_a_frame_naming_a_missing_rig_is_refused(colmap_model, tmp_path):
    model, images = colmap_model
    if (model / "frames.txt").exists():
        _text_field(model / "frames.txt", 4, 1, "3")
    else:
        _pack(model / "frames.bin", 12, "I", 3)
    with pytest.raises(SceneFormatError, match="frame 1 names rig 3") as info:
        import_colmap(model, images, tmp_path / "scene")
    assert info.value.path.stem == "frames" and info.value.field in ("line 4", "entry 1")


@pytest.mark.parametrize("colmap_model", ["text-legacy"], indirect=True)
def test_a_quaternion_written_with_few_digits_is_normalised_with_a_warning(colmap_model, tmp_path, caplog):
    model, images = colmap_model
    lines = (model / "images.txt").read_text().split("\n")
    fields = lines[6].split()
    q = np.array(fields[1:5], float)
    fields[1:5] = [f"{x:.3f}" for x in q]  # |q| - 1 of the order of 1e-3
    lines[6] = " ".join(fields)
    (model / "images.txt").write_text("\n".join(lines))
    with caplog.at_level(logging.WARNING):
        scene = Scene.load(import_colmap(model, images, tmp_path / "scene", test_every=0))
    assert "images.txt [line 7]" in caplog.text and "normalised" in caplog.text
    w, x, y, z = np.round(q, 3) / np.linalg.norm(np.round(q, 3))
    R_cam_world = Rotation.from_quat([x, y, z, w]).as_matrix()
    np.testing.assert_allclose(scene.frames[1].T_world_cam[:3, :3], R_cam_world.T, atol=1e-12)


def test_the_poses_of_a_camera_rig_are_pycolmaps(tmp_path):
    """Two cameras on a rig (the second 0.05 m and 21 degrees off the first): each image's pose is its frame's
    rig_from_world, then its camera's sensor_from_rig, as pycolmap composes them."""
    rec = pycolmap.Reconstruction()
    cameras = [
        pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[9.0, 9.5, 5.2, 3.9], camera_id=1),
        pycolmap.Camera(model="SIMPLE_PINHOLE", width=W, height=H, params=[8.0, 5.0, 4.0], camera_id=2),
    ]
    for camera in cameras:
        rec.add_camera(camera)
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(cameras[0].sensor_id)
    rotation = pycolmap.Rotation3d(Rotation.from_rotvec([0.1, 0.2, -0.3]).as_quat())
    rig.add_sensor(cameras[1].sensor_id, pycolmap.Rigid3d(rotation, [0.05, -0.02, 0.01]))
    rec.add_rig(rig)
    images = tmp_path / "images"
    images.mkdir()
    for fid in (1, 2, 3):
        frame = pycolmap.Frame(frame_id=fid, rig_id=1)
        pairs = []
        for camera in cameras:
            iid = 2 * fid - 2 + camera.camera_id
            image, rig_from_world = _posed_image(fid, camera.camera_id, f"img_{iid:02d}.png")
            image.image_id = iid
            frame.add_data_id(image.data_id)
            pairs.append(image)
            cv2.imwrite(str(images / image.name), np.zeros((H, W, 3), np.uint8))
        frame.rig_from_world = rig_from_world
        rec.add_frame(frame)
        for image in pairs:
            image.frame_id = fid
            rec.add_image(image)
    expected = {}
    for kind in ("text", "binary"):
        (tmp_path / kind).mkdir()
        getattr(rec, f"write_{kind}")(str(tmp_path / kind))
        for image in pycolmap.Reconstruction(str(tmp_path / kind)).images.values():
            expected[image.name] = invert_pose(np.vstack([image.cam_from_world().matrix(), [0, 0, 0, 1]]))
        scene = Scene.load(import_colmap(tmp_path / kind, images, tmp_path / f"scene-{kind}", test_every=0))
        assert len(scene.frames) == 6
        for frame, name in zip(scene.frames, sorted(expected)):
            np.testing.assert_allclose(frame.T_world_cam, expected[name], atol=1e-12)
    assert not np.allclose(expected["img_01.png"], expected["img_02.png"], atol=1e-3)  # the rig's offset is seen


@pytest.mark.parametrize("colmap_model", ["text"], indirect=True)
def test_a_model_too_small_for_the_test_split_says_how_to_train_on_it(colmap_model, tmp_path, capsys):
    model, images = colmap_model
    assert (
        main(
            [
                "import",
                "colmap",
                str(model),
                "--images",
                str(images),
                "--out",
                str(tmp_path / "scene"),
                "--test-every",
                "1",
            ]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no train frame to import" in err and "--test-every 0" in err, err


# --- nerfstudio: implausible distortion, a file too small for the test split -----------------------------------

NS_W, NS_H = 64, 48


def _nerfstudio(root: Path, frames: int = 5, **top) -> Path:
    """transforms.json with an OPENCV camera (top-level keys, overridden by ``top``) over ``frames`` images."""
    root.mkdir(parents=True, exist_ok=True)
    entries = []
    for i in range(frames):
        cv2.imwrite(str(root / f"frame_{i:03d}.png"), np.full((NS_H, NS_W, 3), 30 * i, np.uint8))
        T_world_cam = look_at([2.0 * np.cos(i), 2.0 * np.sin(i), 0.5], [0.0, 0.0, 0.0])
        entries.append({"file_path": f"frame_{i:03d}.png", "transform_matrix": opencv_to_opengl(T_world_cam).tolist()})
    data = {
        "camera_model": "OPENCV",
        "w": NS_W,
        "h": NS_H,
        "fl_x": 50.0,
        "fl_y": 52.0,
        "cx": 32.5,
        "cy": 23.5,
        "frames": entries,
        **top,
    }
    (root / "transforms.json").write_text(json.dumps(data))
    return root


@pytest.mark.parametrize(
    "distortion, field, words",
    [
        ({"k1": 50.0}, "k1", "scales the image corner by 3.5"),  # the issue's: focal 88 px became 1046 px
        ({"k1": -1.0}, "k1", "folds the image back"),  # the radius peaks at 0.385, short of the corner at 0.8
        ({"k1": 0.1, "k2": -3.0}, "k2", "folds the image back"),
        ({"p1": 0.2}, "p1", "moves the image corners by 48%"),
        ({"p2": -50.0}, "p2", "folds the image back"),
    ],
)
def test_implausible_distortion_is_one_error_naming_the_field(tmp_path, distortion, field, words):
    src = _nerfstudio(tmp_path / "ns", **distortion)
    with pytest.raises(SceneFormatError, match=words) as info:
        import_nerfstudio(src, tmp_path / "scene")
    assert info.value.path == src / "transforms.json" and info.value.field == field
    assert not (tmp_path / "scene").exists()


def test_a_frames_implausible_distortion_names_the_frame_and_the_cli_says_it_in_one_line(tmp_path, capsys):
    src = _nerfstudio(tmp_path / "ns")
    data = json.loads((src / "transforms.json").read_text())
    data["frames"][3]["k1"] = 50.0
    (src / "transforms.json").write_text(json.dumps(data))
    assert main(["import", "nerfstudio", str(src), "--out", str(tmp_path / "scene")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "transforms.json [frames[3].k1]" in err and "Traceback" not in err, err


@pytest.mark.parametrize(
    "matrix",
    [
        [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1], [0, 0, 0, 1]],
        [[10**400, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],  # (json writes and reads the int)
    ],
    ids=["a short row", "a number too large for a float"],
)
def test_a_malformed_transform_matrix_is_one_error_naming_the_frame(tmp_path, matrix):
    src = _nerfstudio(tmp_path / "ns")
    data = json.loads((src / "transforms.json").read_text())
    data["frames"][3]["transform_matrix"] = matrix
    (src / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(SceneFormatError, match="expected a 4x4 matrix of numbers") as info:
        import_nerfstudio(src, tmp_path / "scene")
    assert info.value.path == src / "transforms.json" and info.value.field == "frames[3].transform_matrix"
    assert not (tmp_path / "scene").exists()


@pytest.mark.parametrize(
    "edit, field, words",
    [
        (lambda d: d.update(applied_transform=[[10**400, 0, 0, 0]] * 3), "applied_transform", "3x4 matrix of numbers"),
        (lambda d: d["frames"][2].update(mask_path=10**40), "frames[2].mask_path", "expected a path string"),
        (lambda d: [f.update(mask_path="m" * 300 + ".png") for f in d["frames"]], "frames[0].mask_path", "too long"),
    ],
    ids=["an applied_transform number too large for a float", "a mask_path no string", "a mask_path too long"],
)
def test_a_malformed_nerfstudio_field_is_one_error_naming_it(tmp_path, edit, field, words):
    src = _nerfstudio(tmp_path / "ns")
    data = json.loads((src / "transforms.json").read_text())
    edit(data)
    (src / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(SceneFormatError, match=words) as info:
        import_nerfstudio(src, tmp_path / "scene")
    assert info.value.field == field, str(info.value)
    assert not (tmp_path / "scene").exists()


def test_a_real_wide_angle_lens_is_imported(tmp_path):
    """A wide-angle webcam's distortion (k1 -0.28, k2 0.09, the ChArUco tests' lens) and the nerfstudio tests'
    lens pass the plausibility rule."""
    for name, distortion in (
        ("webcam", {"k1": -0.28, "k2": 0.09, "p1": 0.0005, "p2": -0.0003}),
        ("ns", {"k1": -0.15, "k2": 0.04, "p1": 0.003, "p2": -0.002}),
    ):
        scene = Scene.load(import_nerfstudio(_nerfstudio(tmp_path / name, **distortion), tmp_path / f"s-{name}"))
        assert 40 < scene.frames[0].intrinsics.K[0, 0] < 60


def test_one_frame_says_how_to_train_on_it(tmp_path, capsys):
    src = _nerfstudio(tmp_path / "ns", frames=1)
    assert main(["import", "nerfstudio", str(src), "--out", str(tmp_path / "scene")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no train frame to import" in err and "--test-every 0" in err, err
    assert main(["import", "nerfstudio", str(src), "--out", str(tmp_path / "scene"), "--test-every", "0"]) == 0
    assert [f.split for f in Scene.load(tmp_path / "scene").frames] == ["train"]


# --- Blender: OpenEXR frames --------------------------------------------------------------------------------------


def _write_exr(path: Path, rgba: np.ndarray) -> None:
    """A minimal OpenEXR 2 file: one part, scan lines, no compression, float32 channels A B G R (the layout
    Blender's uncompressed RGBA output has; checked with OpenEXR's exrheader and exrmaketiled)."""
    h, w = rgba.shape[:2]

    def attribute(name: str, kind: str, value: bytes) -> bytes:
        return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value

    channels = b"".join(c.encode() + b"\0" + struct.pack("<iB3xii", 2, 0, 1, 1) for c in "ABGR") + b"\0"
    box = struct.pack("<4i", 0, 0, w - 1, h - 1)
    header = (
        b"\x76\x2f\x31\x01"
        + struct.pack("<i", 2)
        + attribute("channels", "chlist", channels)
        + attribute("compression", "compression", b"\0")
        + attribute("dataWindow", "box2i", box)
        + attribute("displayWindow", "box2i", box)
        + attribute("lineOrder", "lineOrder", b"\0")
        + attribute("pixelAspectRatio", "float", struct.pack("<f", 1.0))
        + attribute("screenWindowCenter", "v2f", struct.pack("<2f", 0.0, 0.0))
        + attribute("screenWindowWidth", "float", struct.pack("<f", 1.0))
        + b"\0"
    )
    lines = [
        struct.pack("<ii", y, 16 * w) + b"".join(rgba[y, :, c].astype("<f4").tobytes() for c in (3, 2, 1, 0))
        for y in range(h)
    ]
    offsets = len(header) + 8 * h + np.cumsum([0] + [len(line) for line in lines[:-1]])
    path.write_bytes(header + struct.pack(f"<{h}Q", *offsets) + b"".join(lines))


def test_blender_exr_frames_are_refused_naming_the_file_and_the_conversion(tmp_path, capsys):
    src = tmp_path / "shiny"
    for split in ("train", "test"):
        (src / split).mkdir(parents=True)
        frames = []
        for k in range(2):
            _write_exr(src / split / f"r_{k}.exr", np.random.default_rng(k).uniform(0, 1, (8, 10, 4)))
            T_world_cam = look_at([4.0 * np.cos(k), 4.0 * np.sin(k), 1.0], [0.0, 0.0, 0.0])
            frames.append(
                {"file_path": f"./{split}/r_{k}.exr", "transform_matrix": opencv_to_opengl(T_world_cam).tolist()}
            )
        (src / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
    assert main(["import", "blender", str(src), "--out", str(tmp_path / "scene")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert f"{src / 'train' / 'r_0.exr'} [transforms_train.json frames[0]]" in err
    assert "OpenEXR images are not supported" in err and "convert them to PNG" in err
    assert not (tmp_path / "scene").exists()
