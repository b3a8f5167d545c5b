"""``tacsplat import nerfstudio``: what ns-process-data and instant-ngp write, made here with tiny images, and the
reverse: a tacsplat scene's transforms.json is what nerfstudio's data parser reads."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from tacsplat.cli import main
from tacsplat.datasets import Scene, check_scene
from tacsplat.datasets.nerfstudio import Camera, import_nerfstudio, undistortion
from tacsplat.errors import ConfigError, SceneFormatError
from tacsplat.geometry import look_at, opencv_to_opengl

# ns-process-data's applied_transform (colmap_utils.colmap_to_json): world y and z swapped, then z negated
NS_APPLIED = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]])


def _pose(i: int) -> np.ndarray:
    """OpenCV camera-to-world in the original (e.g. COLMAP) world, looking at a point near the origin."""
    a = 0.7 * i + 0.1
    return look_at([2.0 * np.cos(a), 2.0 * np.sin(a), 0.5 + 0.2 * i], [0.1, -0.05, 0.0])


def _write_png(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if rgb.ndim == 2:
        assert cv2.imwrite(str(path), rgb)
    else:
        assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


# --- instant-ngp: float sizes, no camera_model, every distortion key written as zero, missing images ---------------

NGP_W, NGP_H = 24, 18


def _ngp_image(i: int) -> np.ndarray:
    img = np.zeros((NGP_H, NGP_W, 3), np.uint8)
    img[:, :, 0] = 40 * i
    img[:, :, 1] = np.arange(NGP_W)[None, :] * 10
    img[:, :, 2] = 200
    return img


@pytest.fixture
def ngp_src(tmp_path):
    """colmap2nerf.py's transforms.json: w and h as floats, k1..k4 p1 p2 always present, 6 frames, 2 images missing."""
    src = tmp_path / "ngp"
    frames = []
    for i in range(6):
        name = f"./images/{i:04d}.png"
        if i not in (2, 5):
            _write_png(src / name, _ngp_image(i))
        frames.append(
            {"file_path": name, "sharpness": 120.5 + i, "transform_matrix": opencv_to_opengl(_pose(i)).tolist()}
        )
    data = {
        "camera_angle_x": 1.1,
        "camera_angle_y": 0.9,
        "fl_x": 20.0,
        "fl_y": 20.5,
        "k1": 0.0,
        "k2": 0.0,
        "k3": 0.0,
        "k4": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "is_fisheye": False,
        "cx": 12.0,
        "cy": 9.25,
        "w": float(NGP_W),
        "h": float(NGP_H),
        "aabb_scale": 16,
        "frames": frames[::-1],
    }  # file order is no order: sorted by name
    (src / "transforms.json").write_text(json.dumps(data, indent=2))
    return src


def test_instant_ngp_missing_images_are_one_error_listing_them(ngp_src, tmp_path):
    with pytest.raises(SceneFormatError) as info:
        import_nerfstudio(ngp_src, tmp_path / "scene")
    err = info.value
    assert err.path == ngp_src / "transforms.json" and err.field == "frames"
    assert "2 of 6 frames" in str(err) and "images/0002.png" in str(err) and "images/0005.png" in str(err)
    assert "--skip-missing" in str(err)
    assert not (tmp_path / "scene").exists()


def test_instant_ngp_float_sizes_and_skipped_missing_images(ngp_src, tmp_path, caplog):
    with caplog.at_level(logging.WARNING):
        out = import_nerfstudio(ngp_src, tmp_path / "scene", skip_missing=True, test_every=2, scale=0.1)
    assert "images/0002.png" in caplog.text and "images/0005.png" in caplog.text
    scene = Scene.load(out)
    kept = [0, 1, 3, 4]
    assert [f.split for f in scene.frames] == ["test", "train", "test", "train"]  # every 2nd kept frame, by name
    for frame, i in zip(scene.frames, kept):
        expected = _pose(i)
        expected[:3, 3] *= 0.1
        np.testing.assert_allclose(frame.T_world_cam, expected, atol=1e-12)
        np.testing.assert_array_equal(frame.intrinsics.K, [[20.0, 0, 12.0], [0, 20.5, 9.25], [0, 0, 1]])
        assert (frame.intrinsics.width, frame.intrinsics.height) == (NGP_W, NGP_H)
        np.testing.assert_array_equal(np.rint(scene.load_image(frame) * 255), _ngp_image(i))
    extra = json.loads((out / "scene.json").read_text())["extra"]
    assert extra["importer"] == "nerfstudio" and extra["skipped_missing"] == ["./images/0002.png", "./images/0005.png"]


def test_skip_missing_with_every_image_missing_says_so(ngp_src, tmp_path):
    for png in (ngp_src / "images").glob("*.png"):
        png.unlink()
    with pytest.raises(SceneFormatError) as info:
        import_nerfstudio(ngp_src, tmp_path / "scene", skip_missing=True)
    err = info.value
    assert err.path == ngp_src / "transforms.json" and err.field == "frames"
    assert "the images of all 6 frames are missing: ./images/0000.png" in str(err) and "--test-every" not in str(err)
    assert not (tmp_path / "scene").exists()


def test_the_cli_imports_skipping_missing_images_and_inspect_points_raw_folders_to_it(ngp_src, tmp_path, capsys):
    assert main(["inspect", str(ngp_src)]) == 1  # (no scene: one error line, no summary)
    out, err = capsys.readouterr()
    assert not out and len(err.splitlines()) == 1 and "tacsplat import nerfstudio" in err, err
    assert main(["import", "nerfstudio", str(ngp_src), "--out", str(tmp_path / "scene")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "--skip-missing" in err[0]
    assert (
        main(
            [
                "import",
                "nerfstudio",
                str(ngp_src / "transforms.json"),
                "--out",
                str(tmp_path / "scene"),
                "--skip-missing",
                "--test-every",
                "3",
                "--object",
                "mug",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "frames    4: 2 train, 2 test" in out and "object    mug (source: import)" in out and "problems  none" in out


# --- ns-process-data: OPENCV distortion, applied_transform, masks, split lists -----------------------------------

NS_W, NS_H = 64, 48
NS_K = np.array([[50.0, 0.0, 32.5], [0.0, 52.0, 23.5], [0.0, 0.0, 1.0]])  # pixel centres at +0.5
NS_DIST = {"k1": -0.15, "k2": 0.04, "p1": 0.003, "p2": -0.002}


def _pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The scene as an ideal pinhole camera sees it: smooth colours of normalised image coordinates (x, y)."""
    return np.stack(
        [
            0.5 + 0.4 * np.sin(9 * x + 0.3) * np.cos(7 * y),
            0.5 + 0.4 * np.cos(10 * x - 4 * y),
            0.5 + 0.3 * np.sin(6 * x + 8 * y + 1.0),
        ],
        axis=-1,
    )


def _inside_mask(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return x + 0.4 * y > 0.05


def _undistort_normalised(xd: np.ndarray, yd: np.ndarray, k1, k2, p1, p2) -> tuple[np.ndarray, np.ndarray]:
    """Ideal normalised coordinates of distorted ones (fixed-point inversion of the OpenCV/nerfstudio model)."""
    x, y = xd.copy(), yd.copy()
    for _ in range(100):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2
        x = (xd - (2 * p1 * x * y + p2 * (r2 + 2 * x * x))) / radial
        y = (yd - (p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)) / radial
    return x, y


def _pixel_rays(K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalised coordinates of every pixel centre (at +0.5) under ``K``."""
    v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    return (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]


def _distorted_capture() -> tuple[np.ndarray, np.ndarray]:
    """What the distorted camera records: (RGB uint8 image, mask uint8 0/255)."""
    xd, yd = _pixel_rays(NS_K, NS_W, NS_H)
    x, y = _undistort_normalised(xd, yd, **NS_DIST)
    rgb = np.clip(np.rint(_pattern(x, y) * 255), 0, 255).astype(np.uint8)
    return rgb, np.where(_inside_mask(x, y), 255, 0).astype(np.uint8)


@pytest.fixture
def ns_src(tmp_path):
    """ns-process-data's output for 5 COLMAP images: OPENCV camera, poses in the applied (z-up) frame, a
    mask per frame, a sparse point cloud and sparse depth maps."""
    src = tmp_path / "ns"
    rgb, mask = _distorted_capture()
    frames = []
    for i in range(5):
        _write_png(src / f"images/frame_{i + 1:05d}.png", rgb)
        _write_png(src / f"masks/frame_{i + 1:05d}.png", mask)
        saved = np.vstack([NS_APPLIED, [0, 0, 0, 1]]) @ opencv_to_opengl(_pose(i))
        frames.append(
            {
                "file_path": f"images/frame_{i + 1:05d}.png",
                "transform_matrix": saved.tolist(),
                "colmap_im_id": i + 1,
                "mask_path": f"masks/frame_{i + 1:05d}.png",
                "depth_file_path": f"depths/frame_{i + 1:05d}.png",
            }
        )
    data = {
        "w": NS_W,
        "h": NS_H,
        "fl_x": NS_K[0, 0],
        "fl_y": NS_K[1, 1],
        "cx": NS_K[0, 2],
        "cy": NS_K[1, 2],
        **NS_DIST,
        "camera_model": "OPENCV",
        "frames": frames,
        "applied_transform": NS_APPLIED.tolist(),
        "ply_file_path": "sparse_pc.ply",
    }
    (src / "transforms.json").write_text(json.dumps(data, indent=4))
    return src


def test_ns_process_data_poses_come_back_in_the_original_world(ns_src, tmp_path):
    scene = Scene.load(import_nerfstudio(ns_src, tmp_path / "scene", test_every=4))
    assert [f.split for f in scene.frames] == ["test", "train", "train", "train", "test"]
    for i, frame in enumerate(scene.frames):
        np.testing.assert_allclose(frame.T_world_cam, _pose(i), atol=1e-12)


def test_distorted_images_are_undistorted_with_a_consistent_camera(ns_src, tmp_path):
    """Every pixel of the imported image shows what an ideal camera with the imported K sees along its ray."""
    out = import_nerfstudio(ns_src, tmp_path / "scene")
    scene = Scene.load(out)
    frame = scene.frames[0]
    intr = frame.intrinsics
    assert (intr.width, intr.height) == (NS_W, NS_H)
    x, y = _pixel_rays(intr.K, intr.width, intr.height)
    error = np.abs(scene.load_image(frame) - _pattern(x, y))
    assert error.max() < 0.02 and error.mean() < 0.004, (error.max(), error.mean())
    # the same check fails for the distorted input read with its own K: the test sees distortion
    x0, y0 = _pixel_rays(NS_K, NS_W, NS_H)
    assert np.abs(_distorted_capture()[0] / 255.0 - _pattern(x0, y0)).mean() > 0.015
    # the mask went through the same mapping
    mask = scene.load_mask(frame)
    assert mask.dtype == bool and mask.shape == (NS_H, NS_W)
    assert np.mean(mask != _inside_mask(x, y)) < 0.03
    data = json.loads((out / "transforms.json").read_text())
    assert "k1" not in data or data["k1"] == 0.0
    assert all((out / f["mask_path"]).is_file() for f in data["frames"])


def test_the_undistortion_samples_where_each_pixel_ray_meets_the_distorted_image():
    """Exactly, with pixel centres at +0.5 on both sides (OpenCV's remap indexes them at integers)."""
    camera = Camera(
        NS_K[0, 0],
        NS_K[1, 1],
        NS_K[0, 2],
        NS_K[1, 2],
        NS_W,
        NS_H,
        (NS_DIST["k1"], NS_DIST["k2"], NS_DIST["p1"], NS_DIST["p2"], 0.0),
    )
    intr, (map_x, map_y) = undistortion(camera)
    x, y = _pixel_rays(intr.K, NS_W, NS_H)
    k1, k2, p1, p2 = (NS_DIST[k] for k in ("k1", "k2", "p1", "p2"))
    r2 = x * x + y * y
    xd = x * (1 + k1 * r2 + k2 * r2 * r2) + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * (1 + k1 * r2 + k2 * r2 * r2) + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    np.testing.assert_allclose(map_x, NS_K[0, 0] * xd + NS_K[0, 2] - 0.5, atol=1e-3)
    np.testing.assert_allclose(map_y, NS_K[1, 1] * yd + NS_K[1, 2] - 0.5, atol=1e-3)
    # every pixel of the new camera sees the distorted image (alpha 0: no border to invent)
    assert map_x.min() >= -0.5 and map_x.max() <= NS_W - 0.5 and map_y.min() >= -0.5 and map_y.max() <= NS_H - 0.5
    assert intr.K[0, 1] == 0 and intr.K[2].tolist() == [0, 0, 1]
    no_distortion = Camera(50.0, 52.0, 32.5, 23.5, NS_W, NS_H, (0.0,) * 5)
    assert undistortion(no_distortion)[1] is None
    np.testing.assert_array_equal(undistortion(no_distortion)[0].K, [[50.0, 0, 32.5], [0, 52.0, 23.5], [0, 0, 1]])


def test_what_is_not_imported_is_said_and_recorded(ns_src, tmp_path, caplog):
    with caplog.at_level(logging.WARNING):
        out = import_nerfstudio(ns_src, tmp_path / "scene")
    assert "depth_file_path" in caplog.text and "ply_file_path" in caplog.text
    extra = json.loads((out / "scene.json").read_text())["extra"]
    assert extra["not_imported"] == {"depth_file_path": 5, "ply_file_path": "sparse_pc.ply"}
    assert extra["applied_transform"] == NS_APPLIED.tolist()


def _edit(src: Path, edit) -> None:
    path = src / "transforms.json"
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def test_split_lists_decide_the_splits(ns_src, tmp_path):
    _edit(
        ns_src,
        lambda d: d.update(
            train_filenames=["images/frame_00001.png", "./images/frame_00003.png", "images/frame_00004.png"],
            val_filenames=["images/frame_00002.png"],
            test_filenames=["images/frame_00002.png", "images/frame_00005.png"],
        ),
    )
    scene = Scene.load(import_nerfstudio(ns_src, tmp_path / "scene", test_every=1))  # the lists win over the rule
    assert [f.split for f in scene.frames] == ["train", "test", "train", "train", "test"]


@pytest.mark.parametrize(
    "lists, field, words",
    [
        (
            {"train_filenames": ["images/frame_00001.png", "images/nope.png"], "test_filenames": []},
            "train_filenames",
            "images/nope.png",
        ),
        (
            {
                "train_filenames": ["images/frame_00001.png", "images/frame_00002.png"],
                "test_filenames": ["images/frame_00002.png"],
            },
            "test_filenames",
            "also in train_filenames",
        ),
    ],
)
def test_split_lists_naming_unknown_or_shared_frames_are_refused(ns_src, tmp_path, lists, field, words):
    _edit(ns_src, lambda d: d.update(lists))
    with pytest.raises(SceneFormatError, match=words) as info:
        import_nerfstudio(ns_src, tmp_path / "scene")
    assert info.value.field == field
    assert not (tmp_path / "scene").exists()


@pytest.mark.parametrize(
    "edit, field, words",
    [
        (lambda d: d.update(camera_model="OPENCV_FISHEYE"), "camera_model", "OPENCV_FISHEYE"),
        (lambda d: d.update(k4=0.01), "k4", "k4"),
        (lambda d: d.update(w=64.5), "w", "64.5"),
        (lambda d: d["frames"][1].pop("mask_path"), "frames[1].mask_path", "every frame or none"),
        (
            lambda d: d.update(applied_transform=[[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0]]),
            "applied_transform",
            "rigid",
        ),
        (lambda d: d["frames"][3].update(transform_matrix=[[1, 0, 0], [0, 1, 0]]), "frames[3].transform_matrix", "4x4"),
        (lambda d: d["frames"][3]["transform_matrix"][0].__setitem__(3, 1e6), "frames[3].transform_matrix", r"1e\+06"),
        (lambda d: d.update(applied_scale=1e-7), "applied_scale", r"frames\[0\].*metres from the origin"),
    ],
)
def test_what_a_scene_cannot_hold_is_one_error_naming_the_field(ns_src, tmp_path, edit, field, words):
    _edit(ns_src, edit)
    with pytest.raises(SceneFormatError, match=words) as info:
        import_nerfstudio(ns_src, tmp_path / "scene")
    assert info.value.path == ns_src / "transforms.json" and info.value.field == field
    assert not (tmp_path / "scene").exists()


def test_a_mask_of_another_size_names_the_mask(ns_src, tmp_path):
    _write_png(ns_src / "masks/frame_00003.png", np.zeros((10, 10), np.uint8))
    with pytest.raises(SceneFormatError, match="10x10") as info:
        import_nerfstudio(ns_src, tmp_path / "scene")
    assert info.value.path == ns_src / "masks/frame_00003.png"


def test_the_alpha_of_a_mask_is_no_part_of_it(ns_src, tmp_path):
    """An RGBA mask saved with an opaque alpha (as editors do) keeps only the pixels its colour says to use."""
    grey = Scene.load(import_nerfstudio(ns_src, tmp_path / "grey"))
    for path in (ns_src / "masks").iterdir():
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(path), np.dstack([mask, mask, mask, np.full_like(mask, 255)]))
    rgba = Scene.load(import_nerfstudio(ns_src, tmp_path / "rgba"))
    for a, b in zip(grey.frames, rgba.frames):
        assert 0 < grey.load_mask(a).mean() < 1
        np.testing.assert_array_equal(rgba.load_mask(b), grey.load_mask(a))


def test_bad_options_are_config_errors(ns_src, tmp_path):
    with pytest.raises(ConfigError, match="test_every"):
        import_nerfstudio(ns_src, tmp_path / "scene", test_every=-1)
    with pytest.raises(ConfigError, match="scale"):
        import_nerfstudio(ns_src, tmp_path / "scene", scale=0.0)
    with pytest.raises(ConfigError, match=r"scale: 1e\+06 metres per unit puts frames\[0\] .*from the origin"):
        import_nerfstudio(ns_src, tmp_path / "scene", scale=1e6)
    with pytest.raises(SceneFormatError, match="transforms.json"):
        import_nerfstudio(tmp_path / "nowhere", tmp_path / "scene")


# --- the reverse: a tacsplat scene is nerfstudio input ---------------------------------------------------------

NERFSTUDIO_CAMERA_MODELS = (
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
    "OPENCV_FISHEYE",
    "EQUIRECTANGULAR",
    "OMNIDIRECTIONALSTEREO_L",
    "OMNIDIRECTIONALSTEREO_R",
    "VR180_L",
    "VR180_R",
    "ORTHOPHOTO",
    "FISHEYE624",
)  # nerfstudio's CAMERA_MODEL_TO_TYPE keys


def nerfstudio_parse(data_dir: Path, split: str) -> dict:
    """The reading logic of nerfstudio's ``Nerfstudio._generate_dataparser_outputs`` (nerfstudio_dataparser.py,
    without its downscaling, orientation and scaling): which keys it needs and how it picks a split."""
    meta = json.loads((data_dir / "transforms.json").read_text())
    fixed = {key: key in meta for key in ("fl_x", "fl_y", "cx", "cy", "h", "w")}
    distort_fixed = any(key in meta for key in ("k1", "k2", "k3", "p1", "p2", "distortion_params"))
    frames = sorted(meta["frames"], key=lambda f: str(data_dir / Path(f["file_path"])))
    per_frame = {key: [] for key in fixed}
    image_filenames, mask_filenames, poses = [], [], []
    for frame in frames:
        for key, is_fixed in fixed.items():
            if not is_fixed:
                assert key in frame, f"{key} not specified in frame"
                per_frame[key].append((int if key in "hw" else float)(frame[key]))
        if not distort_fixed:
            [float(frame.get(k, 0.0)) for k in ("k1", "k2", "k3", "k4", "p1", "p2")]
        fname = data_dir / Path(frame["file_path"])
        assert fname.is_file()
        image_filenames.append(fname)
        poses.append(np.array(frame["transform_matrix"]))
        if "mask_path" in frame:
            mask_filenames.append(data_dir / Path(frame["mask_path"]))
    assert len(mask_filenames) in (0, len(image_filenames)), "mask_path on every frame or none"
    has_split_files_spec = any(f"{s}_filenames" in meta for s in ("train", "val", "test"))
    assert f"{split}_filenames" in meta or not has_split_files_spec, f"list of filenames for split {split} is missing"
    split_filenames = {data_dir / Path(x) for x in meta[f"{split}_filenames"]}
    assert not split_filenames.difference(image_filenames), "some split filenames were not found"
    indices = [i for i, path in enumerate(image_filenames) if path in split_filenames]
    camera_model = meta.get("camera_model", "OPENCV")
    assert camera_model in NERFSTUDIO_CAMERA_MODELS
    poses = np.array(poses).astype(np.float32)
    assert poses.shape[1:] == (4, 4)
    return {
        "indices": indices,
        "poses": poses[indices],
        "images": [image_filenames[i] for i in indices],
        "masks": [mask_filenames[i] for i in indices] if mask_filenames else None,
        "intrinsics": {k: meta[k] if v else [per_frame[k][i] for i in indices] for k, v in fixed.items()},
    }


def test_a_tacsplat_scene_is_what_nerfstudio_parses_and_imports_back_identically(scene_dir, tmp_path, h):
    source = Scene.load(scene_dir)
    for split, ours in (("train", "train"), ("val", "test"), ("test", "test")):
        parsed = nerfstudio_parse(scene_dir, split)
        frames = source.split(ours)
        assert parsed["images"] == [scene_dir / f.file_path for f in frames]
        np.testing.assert_allclose(parsed["poses"], [opencv_to_opengl(f.T_world_cam) for f in frames], atol=1e-6)
        assert parsed["intrinsics"]["fl_x"] == h.intrinsics().fx and parsed["intrinsics"]["w"] == h.WIDTH
        assert parsed["masks"] is None
    copy = Scene.load(import_nerfstudio(scene_dir, tmp_path / "copy"))
    assert [(f.split, f.file_path) for f in copy.frames] == [(f.split, f.file_path) for f in source.frames]
    for a, b in zip(copy.frames, source.frames):
        np.testing.assert_allclose(a.T_world_cam, b.T_world_cam, rtol=0, atol=1e-15)  # re-orthonormalised
        np.testing.assert_array_equal(a.intrinsics.K, b.intrinsics.K)
        np.testing.assert_array_equal(copy.load_image(a), source.load_image(b))


def test_an_imported_scene_with_masks_is_what_nerfstudio_parses(ns_src, tmp_path):
    out = import_nerfstudio(ns_src, tmp_path / "scene", test_every=2)
    scene = Scene.load(out)
    parsed = nerfstudio_parse(out, "train")
    assert parsed["masks"] == [out / f.mask_path for f in scene.split("train")]
    assert check_scene(out)[1] == []
