"""Blender/NeRF-synthetic and COLMAP importers on small fixtures built here."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pycolmap
import pytest

from tacsplat.cli import main
from tacsplat.datasets import Scene
from tacsplat.datasets.blender import import_blender
from tacsplat.datasets.colmap import import_colmap
from tacsplat.errors import SceneFormatError
from tacsplat.geometry import invert_pose, look_at, opencv_to_opengl

W, H = 10, 8
ANGLE_X = 0.6911112070083618  # NeRF synthetic's camera_angle_x


def _blender_pose(i: int) -> np.ndarray:
    """OpenGL camera-to-world as Blender writes it, looking at the origin."""
    a = 0.9 * i + 0.2
    return opencv_to_opengl(look_at([4.0 * np.cos(a), 4.0 * np.sin(a), 1.0 + 0.3 * i], [0.0, 0.0, 0.0]))


def _rgba(i: int) -> np.ndarray:
    """RGBA: transparent left third, opaque colour in the middle, half-transparent right part."""
    img = np.zeros((H, W, 4), np.uint8)
    img[:, :, :3] = [200, 10 + i, 60]
    img[:, 3:6, 3] = 255
    img[:, 6:, 3] = 128
    return img


@pytest.fixture
def blender_src(tmp_path):
    src = tmp_path / "lego"
    counts = {"train": 3, "val": 2, "test": 2}
    for split, n in counts.items():
        (src / split).mkdir(parents=True)
        frames = []
        for k in range(n):
            i = len(frames) + 10 * list(counts).index(split)
            cv2.imwrite(str(src / split / f"r_{k}.png"), cv2.cvtColor(_rgba(i), cv2.COLOR_RGBA2BGRA))
            frames.append(
                {
                    "file_path": f"./{split}/r_{k}",
                    "rotation": 0.012566370614359171,
                    "transform_matrix": _blender_pose(i).tolist(),
                }
            )
        (src / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": ANGLE_X, "frames": frames}))
    return src


def test_blender_import_poses_intrinsics_and_compositing(blender_src, tmp_path):
    out = import_blender(blender_src, tmp_path / "scene", background_rgb=(255, 255, 255))
    scene = Scene.load(out)
    assert [f.split for f in scene.frames] == ["train"] * 3 + ["test"] * 2
    sources = [0, 1, 2, 20, 21]
    for frame, i in zip(scene.frames, sources):
        np.testing.assert_allclose(opencv_to_opengl(frame.T_world_cam), _blender_pose(i), atol=1e-6)
        # independently of the conversion helpers: the OpenCV camera looks (+z) at the origin, image-down (+y) is world-down
        c, z, y = frame.T_world_cam[:3, 3], frame.T_world_cam[:3, 2], frame.T_world_cam[:3, 1]
        assert z @ (-c / np.linalg.norm(c)) > 0.999 and y[2] < 0
    intr = scene.intrinsics
    f = 0.5 * W / np.tan(0.5 * ANGLE_X)
    np.testing.assert_allclose(intr.K, [[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    assert (intr.width, intr.height) == (W, H)
    img = np.rint(scene.load_image(scene.frames[1]) * 255).astype(int)
    assert (img[:, :3] == 255).all()  # transparent -> background
    assert (img[:, 3:6] == [200, 11, 60]).all()  # opaque -> its colour
    a = 128 / 255
    assert (img[:, 6:] == np.rint(np.array([200, 11, 60]) * a + 255 * (1 - a))).all()
    assert (out / "images" / "000000.png").is_file()


def test_blender_import_cli_black_background_and_val_split(blender_src, tmp_path, capsys):
    out = tmp_path / "scene"
    assert (
        main(
            [
                "import",
                "blender",
                str(blender_src),
                "--out",
                str(out),
                "--background",
                "black",
                "--test-split",
                "val",
                "--scale",
                "0.05",
            ]
        )
        == 0
    )
    assert "2 test" in capsys.readouterr().out
    scene = Scene.load(out)
    expected = _blender_pose(10)
    expected[:3, 3] *= 0.05
    np.testing.assert_allclose(opencv_to_opengl(scene.split("test")[0].T_world_cam), expected, atol=1e-6)
    img = np.rint(scene.load_image(scene.frames[0]) * 255).astype(int)
    assert (img[:, :3] == 0).all()
    assert (img[:, 6:] == np.rint(np.array([200, 10, 60]) * 128 / 255)).all()
    assert main(["import", "blender", str(blender_src), "--out", str(tmp_path / "x"), "--background", "1,2"]) == 2
    assert "--background: background must be white, black or R,G,B with integers 0-255, got '1,2'" in (
        capsys.readouterr().err
    )


def test_blender_import_errors_name_the_file_and_clean_up(blender_src, tmp_path):
    data = json.loads((blender_src / "transforms_train.json").read_text())
    data["frames"][1]["transform_matrix"][0][0] *= 1.5
    (blender_src / "transforms_train.json").write_text(json.dumps(data))
    with pytest.raises(SceneFormatError) as info:
        import_blender(blender_src, tmp_path / "scene")
    assert info.value.path.name == "transforms_train.json" and info.value.field == "frames[1].transform_matrix"
    assert not (tmp_path / "scene").exists()  # a failed import leaves nothing behind
    (blender_src / "transforms_test.json").unlink()
    with pytest.raises(SceneFormatError, match="transforms_test.json"):
        import_blender(blender_src, tmp_path / "scene")


SHORT_ROW = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1], [0, 0, 0, 1]]
TOO_LARGE = [[10**400, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]  # (json writes and reads the int)


@pytest.mark.parametrize(
    "split, edit, field, words",
    [
        ("train", lambda frames: frames[1].update(transform_matrix=SHORT_ROW), "frames[1].transform_matrix", "4x4"),
        ("train", lambda frames: frames[1].update(transform_matrix=TOO_LARGE), "frames[1].transform_matrix", "4x4"),
        ("train", lambda frames: frames.__setitem__(0, "./train/r_0"), "frames[0].file_path", "an object"),
        ("test", lambda frames: frames.__setitem__(0, 7), "frames[0].file_path", "an object"),
    ],
    ids=["a short row", "a number too large for a float", "a first frame no object", "a first test frame no object"],
)
def test_a_malformed_blender_frame_is_one_error_naming_the_file_and_field(
    blender_src, tmp_path, split, edit, field, words
):
    index = blender_src / f"transforms_{split}.json"
    data = json.loads(index.read_text())
    edit(data["frames"])
    index.write_text(json.dumps(data))
    with pytest.raises(SceneFormatError, match=words) as info:
        import_blender(blender_src, tmp_path / "scene")
    assert info.value.path == index and info.value.field == field
    assert not (tmp_path / "scene").exists()


def _colmap_fixture(root, models=("PINHOLE", "SIMPLE_PINHOLE"), distortion=0.0):
    """A COLMAP model of known cameras (written as text and binary) and its images."""
    rec = pycolmap.Reconstruction()
    params = {
        "PINHOLE": [9.0, 9.5, 5.2, 3.9],
        "SIMPLE_PINHOLE": [8.0, 5.0, 4.0],
        "OPENCV": [9.0, 9.5, 5.2, 3.9, distortion, 0.0, 0.0, 0.0],
        "SIMPLE_RADIAL": [8.0, 5.0, 4.0, distortion],
        "FULL_OPENCV": [9.0, 9.5, 5.2, 3.9] + [0.0] * 8,
    }
    for cid, model in enumerate(models, start=1):
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(model=model, width=W, height=H, params=params[model], camera_id=cid)
        )
    images_dir = root / "images"
    images_dir.mkdir(parents=True)
    poses = {}
    for iid in range(1, 6):
        T_world_cam = look_at([np.cos(iid), np.sin(iid), 0.3 * iid], [0.1, 0.0, 0.0])
        name = f"img_{iid:02d}.png"
        poses[name] = T_world_cam
        cam_from_world = pycolmap.Rigid3d(invert_pose(T_world_cam)[:3, :4])
        image = pycolmap.Image(name=name, camera_id=1 + iid % len(models), image_id=iid)
        rec.add_image_with_trivial_frame(image, cam_from_world)
        rgb = np.full((H, W, 3), [iid * 20, 100, 7], np.uint8)
        cv2.imwrite(str(images_dir / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    for kind in ("text", "binary"):
        (root / kind).mkdir()
        getattr(rec, f"write_{kind}")(str(root / kind))
    return rec, images_dir, poses


@pytest.mark.parametrize("kind", ["text", "binary"])
def test_colmap_import_round_trips_poses_and_cameras(tmp_path, kind):
    rec, images_dir, poses = _colmap_fixture(tmp_path / "colmap")
    assert {p.suffix for p in (tmp_path / "colmap" / kind).iterdir()} == {".txt" if kind == "text" else ".bin"}
    out = import_colmap(tmp_path / "colmap" / kind, images_dir, tmp_path / "scene", test_every=2, scale=1.0)
    scene = Scene.load(out)
    names = sorted(poses)
    assert [f.split for f in scene.frames] == ["test", "train", "test", "train", "test"]
    for frame, name in zip(scene.frames, names):
        np.testing.assert_allclose(frame.T_world_cam, poses[name], atol=1e-6)
        iid = int(name[4:6])
        cam = rec.cameras[1 + iid % 2]
        np.testing.assert_allclose(frame.intrinsics.K, cam.calibration_matrix(), atol=1e-12)
        np.testing.assert_array_equal(np.rint(scene.load_image(frame)[0, 0] * 255), [iid * 20, 100, 7])
    meta = json.loads((out / "scene.json").read_text())
    assert meta["extra"]["colmap_names"] == names and meta["source"] == "import"


def test_colmap_import_scale_and_zero_distortion_models(tmp_path):
    _, images_dir, poses = _colmap_fixture(tmp_path / "colmap", models=("OPENCV", "SIMPLE_RADIAL"))
    scene = Scene.load(
        import_colmap(tmp_path / "colmap" / "binary", images_dir, tmp_path / "scene", test_every=0, scale=0.25)
    )
    assert all(f.split == "train" for f in scene.frames)
    for frame, name in zip(scene.frames, sorted(poses)):
        np.testing.assert_allclose(frame.T_world_cam[:3, :3], poses[name][:3, :3], atol=1e-6)
        np.testing.assert_allclose(frame.T_world_cam[:3, 3], 0.25 * poses[name][:3, 3], atol=1e-6)


@pytest.mark.parametrize(
    "models, distortion, words",
    [
        (("OPENCV",), 0.05, "camera model OPENCV has non-zero distortion"),
        (("FULL_OPENCV",), 0.0, "camera model FULL_OPENCV is not supported"),
    ],
)
def test_colmap_import_rejects_distorted_cameras_naming_the_model(tmp_path, models, distortion, words):
    _, images_dir, _ = _colmap_fixture(tmp_path / "colmap", models=models, distortion=distortion)
    with pytest.raises(SceneFormatError, match=words) as info:
        import_colmap(tmp_path / "colmap" / "text", images_dir, tmp_path / "scene")
    assert info.value.path.name == "cameras.txt" and info.value.field == "line 4" and "camera 1" in str(info.value)
    assert not (tmp_path / "scene").exists()


def test_colmap_import_cli_and_missing_images(tmp_path, capsys):
    _, images_dir, _ = _colmap_fixture(tmp_path / "colmap")
    assert (
        main(
            [
                "import",
                "colmap",
                str(tmp_path / "colmap" / "text"),
                "--images",
                str(images_dir),
                "--out",
                str(tmp_path / "scene"),
            ]
        )
        == 0
    )
    assert "1 test" in capsys.readouterr().out  # every 8th image: only the first of five
    (images_dir / "img_03.png").unlink()
    with pytest.raises(SceneFormatError, match="img_03.png"):
        import_colmap(tmp_path / "colmap" / "text", images_dir, tmp_path / "scene2")
    with pytest.raises(SceneFormatError, match="not a readable COLMAP sparse model"):
        import_colmap(tmp_path / "nowhere", images_dir, tmp_path / "scene3")


def _import_commands(blender_src, colmap_root, images_dir):
    return {
        "blender": lambda out, *extra: ["import", "blender", str(blender_src), "--out", str(out), *extra],
        "colmap": lambda out, *extra: [
            "import",
            "colmap",
            str(colmap_root / "text"),
            "--images",
            str(images_dir),
            "--out",
            str(out),
            *extra,
        ],
    }


def _one_error_line(capsys, *words, prefix: str = "error: ") -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(prefix) and "Traceback" not in err, err
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


def test_import_into_an_unusable_out_or_with_a_bad_scale_is_one_error(blender_src, tmp_path, capsys, monkeypatch):
    import os

    _, images_dir, _ = _colmap_fixture(tmp_path / "colmap")
    commands = _import_commands(blender_src, tmp_path / "colmap", images_dir)
    a_file = tmp_path / "a_file"
    a_file.write_text("not a folder")
    for name, command in commands.items():
        assert main(command(a_file)) == 1, name
        _one_error_line(capsys, "--out", "is a file")
        assert main(command(a_file / "scene")) == 1, name
        _one_error_line(capsys, "--out", "which is a file")
        assert a_file.read_text() == "not a folder"
        for scale in ("0", "-2", "nan", "inf"):
            assert main(command(tmp_path / f"{name}-scale", "--scale", scale)) == 2, (name, scale)  # a usage error
            _one_error_line(capsys, "--scale", "positive", prefix=f"tacsplat import {name}: error: ")
            assert not (tmp_path / f"{name}-scale").exists()
    assert main(commands["colmap"](tmp_path / "every", "--test-every", "-1")) == 2
    _one_error_line(capsys, "--test-every", ">= 0", prefix="tacsplat import colmap: error: ")
    real_access = os.access
    monkeypatch.setattr(
        os, "access", lambda path, mode, **kw: False if "locked" in str(path) else real_access(path, mode)
    )
    for name, command in commands.items():
        assert main(command(tmp_path / "locked")) == 1, name
        _one_error_line(capsys, "--out", "is not writable")


def test_an_import_into_a_folder_another_process_writes_is_refused(blender_src, tmp_path, capsys):
    from tacsplat.datasets.outputs import claim_output_dir

    out = tmp_path / "scene"
    with claim_output_dir(out):
        assert main(["import", "blender", str(blender_src), "--out", str(out)]) == 1
        _one_error_line(capsys, "another tacsplat process")
    assert main(["import", "blender", str(blender_src), "--out", str(out)]) == 0  # the lock file is no content
    assert len(Scene.load(out).frames) == 5
    capsys.readouterr()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("x")
    assert main(["import", "blender", str(blender_src), "--out", str(mine)]) == 1
    _one_error_line(capsys, "is not an empty folder")
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]  # not even a lock file left among them
