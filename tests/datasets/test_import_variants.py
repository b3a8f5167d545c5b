"""What Blender and nerfstudio/instant-ngp transforms files write beyond the basics: explicit intrinsics in a
Blender dataset (the BlenderNeRF add-on, a lens shift), RGBA images in a nerfstudio dataset, and file paths
without an extension (instant-ngp, NeRF synthetic). Tiny datasets are made here."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tacsplat.cli import main
from tacsplat.datasets import Scene
from tacsplat.datasets.blender import import_blender
from tacsplat.datasets.nerfstudio import import_nerfstudio
from tacsplat.errors import SceneFormatError
from tacsplat.geometry import opencv_to_opengl

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from paper_datasets import ANGLE_X, ring_pose  # noqa: E402

W, H = 24, 16


def _pose_gl(i: int) -> np.ndarray:
    """OpenGL camera-to-world as Blender writes it, looking at the origin."""
    return opencv_to_opengl(ring_pose(i, 4, distance=3.0))


def _rgba(i: int) -> np.ndarray:
    """RGBA [H, W, 4]: green under a transparent left third, opaque colour in the middle, half alpha on the right."""
    img = np.zeros((H, W, 4), np.uint8)
    img[:, :, :3] = [200, 10 + i, 60]
    img[:, :8] = [0, 255, 0, 0]
    img[:, 8:16, 3] = 255
    img[:, 16:, 3] = 128
    return img


def _write(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR if img.shape[2] == 3 else cv2.COLOR_RGBA2BGRA)
    assert cv2.imwrite(str(path), img)


def _blender(root: Path, top: dict | None = None, per_frame: dict | None = None) -> Path:
    """A Blender dataset of 2 train and 2 test views, ``top`` added to both files' top level and
    ``per_frame[i]`` to frame i of each."""
    for split in ("train", "test"):
        frames = []
        for k in range(2):
            _write(root / split / f"r_{k}.png", _rgba(k))
            frame = {"file_path": f"./{split}/r_{k}", "transform_matrix": _pose_gl(k).tolist()}
            frames.append({**frame, **(per_frame or {}).get(k, {})})
        data = {"camera_angle_x": ANGLE_X, **(top or {}), "frames": frames}
        (root / f"transforms_{split}.json").write_text(json.dumps(data))
    return root


def _K(fx, fy, cx, cy) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


# --- import blender: explicit intrinsics -----------------------------------------------------------------------


def test_blender_without_intrinsics_keys_keeps_the_field_of_view_camera(tmp_path):
    scene = Scene.load(import_blender(_blender(tmp_path / "bl"), tmp_path / "scene"))
    f = W / 2 / np.tan(ANGLE_X / 2)
    for frame in scene.frames:
        np.testing.assert_array_equal(frame.intrinsics.K, _K(f, f, W / 2, H / 2))


def test_blender_explicit_intrinsics_win_over_the_field_of_view(tmp_path):
    """BlenderNeRF writes fl_x fl_y cx cy w h (a lens shift moves cx cy) and every distortion key as 0."""
    zeros = dict.fromkeys(("k1", "k2", "k3", "k4", "p1", "p2"), 0.0)
    top = {"camera_angle_y": 0.5, "fl_x": 30.0, "fl_y": 31.0, "cx": 9.0, "cy": 10.5, "w": W, "h": H, **zeros}
    scene = Scene.load(import_blender(_blender(tmp_path / "bl", top), tmp_path / "scene"))
    assert len(scene.frames) == 4
    for frame in scene.frames:
        np.testing.assert_array_equal(frame.intrinsics.K, _K(30.0, 31.0, 9.0, 10.5))
        assert (frame.intrinsics.width, frame.intrinsics.height) == (W, H)


def test_blender_per_frame_intrinsics_and_camera_angle_y(tmp_path):
    per_frame = {1: {"fl_x": 25.0, "cx": 13.0, "cy": 7.0}}
    src = _blender(tmp_path / "bl", {"camera_angle_y": 0.5}, per_frame)
    scene = Scene.load(import_blender(src, tmp_path / "scene"))
    fx, fy = W / 2 / np.tan(ANGLE_X / 2), H / 2 / np.tan(0.5 / 2)
    for split in ("train", "test"):
        first, second = scene.split(split)
        np.testing.assert_allclose(first.intrinsics.K, _K(fx, fy, W / 2, H / 2), rtol=1e-12)
        np.testing.assert_allclose(second.intrinsics.K, _K(25.0, fy, 13.0, 7.0), rtol=1e-12)


def test_blender_w_and_h_other_than_the_image_size_name_the_file_and_field(tmp_path):
    src = _blender(tmp_path / "bl", {"fl_x": 30.0, "w": W - 4, "h": H})
    with pytest.raises(SceneFormatError) as info:
        import_blender(src, tmp_path / "scene")
    err = info.value
    assert err.path == src / "train" / "r_0.png" and err.field == "transforms_train.json frames[0]"
    assert f"image is {W}x{H}, but its camera (w x h in transforms_train.json) is {W - 4}x{H}" in str(err)
    assert not (tmp_path / "scene").exists()


def test_blender_lens_distortion_is_refused_naming_the_field(tmp_path):
    src = _blender(tmp_path / "bl", per_frame={1: {"k1": 0.1}})
    with pytest.raises(SceneFormatError, match="lens distortion") as info:
        import_blender(src, tmp_path / "scene")
    assert info.value.path == src / "transforms_train.json" and info.value.field == "frames[1].k1"
    assert not (tmp_path / "scene").exists()


# --- import nerfstudio: RGBA images and file paths without an extension ----------------------------------------


def _nerfstudio(root: Path, images: list[np.ndarray], suffix: str = ".png", **top) -> Path:
    """A transforms.json (pinhole fl_x 30) whose frames are ``images``, each ``images/000k`` + ``suffix``."""
    frames = []
    for k, img in enumerate(images):
        _write(root / "images" / f"{k:04d}.png", img)
        frames.append({"file_path": f"images/{k:04d}{suffix}", "transform_matrix": _pose_gl(k).tolist()})
    data = {"fl_x": 30.0, "fl_y": 30.0, "cx": W / 2, "cy": H / 2, "w": W, "h": H, **top, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(data))
    return root


def _over(rgba: np.ndarray, background) -> np.ndarray:
    a = rgba[:, :, 3:4] / 255.0
    return np.rint(rgba[:, :, :3] * a + np.asarray(background, float) * (1 - a)).astype(int)


@pytest.mark.parametrize("background", [(255, 255, 255), (0, 0, 0), (10, 20, 250)])
def test_nerfstudio_rgba_images_are_composited_onto_the_background(tmp_path, background):
    """The green under transparent pixels is no training data: straight alpha over the background, as import
    blender composites (white by default) and as nerfstudio and instant-ngp do."""
    src = _nerfstudio(tmp_path / "ns", [_rgba(k) for k in range(3)])
    options = {} if background == (255, 255, 255) else {"background_rgb": background}
    out = import_nerfstudio(src, tmp_path / "scene", test_every=0, **options)
    scene = Scene.load(out)
    for k, frame in enumerate(scene.frames):
        img = np.rint(scene.load_image(frame) * 255).astype(int)
        np.testing.assert_array_equal(img, _over(_rgba(k), background))
        assert (img[:, :8] == background).all()
    assert json.loads((out / "scene.json").read_text())["extra"]["background_rgb"] == list(background)


def test_nerfstudio_opaque_rgba_is_the_rgb_image_and_a_mask_stays_the_mask(tmp_path):
    rgb = [np.random.default_rng(k).integers(0, 256, (H, W, 3), dtype=np.uint8) for k in range(3)]
    opaque = [np.dstack([img, np.full((H, W), 255, np.uint8)]) for img in rgb]
    distortion = {"camera_model": "OPENCV", "k1": -0.05, "p1": 0.001}
    plain = Scene.load(import_nerfstudio(_nerfstudio(tmp_path / "rgb", rgb, **distortion), tmp_path / "a"))
    src = _nerfstudio(tmp_path / "rgba", opaque, **distortion)
    mask = np.zeros((H, W), np.uint8)
    mask[4:12, 5:20] = 255
    _write(src / "masks" / "m.png", mask)
    data = json.loads((src / "transforms.json").read_text())
    for frame in data["frames"]:
        frame["mask_path"] = "masks/m.png"
    (src / "transforms.json").write_text(json.dumps(data))
    masked = Scene.load(import_nerfstudio(src, tmp_path / "b", background_rgb=(0, 0, 255)))
    for a, b in zip(plain.frames, masked.frames):
        np.testing.assert_array_equal(masked.load_image(b), plain.load_image(a))
        assert masked.load_mask(b)[8, 12] and not masked.load_mask(b)[0, 0]


def test_nerfstudio_cli_background_option(tmp_path, capsys):
    src = _nerfstudio(tmp_path / "ns", [_rgba(k) for k in range(3)])
    args = ["import", "nerfstudio", str(src), "--test-every", "0"]
    assert main([*args, "--out", str(tmp_path / "x"), "--background", "1,2"]) == 2
    assert "--background: background must be white, black or R,G,B" in capsys.readouterr().err
    assert main([*args, "--out", str(tmp_path / "scene"), "--background", "black"]) == 0
    scene = Scene.load(tmp_path / "scene")
    assert (np.rint(scene.load_image(scene.frames[0]) * 255)[:, :8] == 0).all()


def test_nerfstudio_file_paths_without_an_extension_name_the_image(tmp_path):
    """instant-ngp (and NeRF synthetic's ./train/r_0) leave the extension off; split lists name frames so too."""
    images = [_rgba(k)[:, :, :3] for k in range(4)]
    lists = {"train_filenames": ["images/0000", "images/0001", "images/0003"], "test_filenames": ["images/0002"]}
    src = _nerfstudio(tmp_path / "ns", images, suffix="", **lists)
    out = import_nerfstudio(src, tmp_path / "scene")
    scene = Scene.load(out)
    assert [f.split for f in scene.frames] == ["train", "train", "test", "train"]
    for k, frame in enumerate(scene.frames):
        np.testing.assert_array_equal(np.rint(scene.load_image(frame) * 255), images[k])
    assert json.loads((out / "scene.json").read_text())["extra"]["nerfstudio_names"][0] == "images/0000"


def test_nerfstudio_a_missing_image_without_an_extension_is_named_as_written(tmp_path):
    src = _nerfstudio(tmp_path / "ns", [_rgba(k)[:, :, :3] for k in range(3)], suffix="")
    (src / "images" / "0001.png").unlink()
    with pytest.raises(SceneFormatError, match="the images of 1 of 3 frames are missing: images/0001 "):
        import_nerfstudio(src, tmp_path / "scene")
