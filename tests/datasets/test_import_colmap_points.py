"""`import colmap`: the model's 3D points kept as the scene's sparse points, images of a downscaled folder, and the
hint for a folder one level above its model. The models are written here as COLMAP text files (binary by
pycolmap), with 2D observations projected by pycolmap's own camera model."""

from __future__ import annotations

import json
import logging

import cv2
import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from tacsplat.datasets import Scene, SceneWriter, copy_scene
from tacsplat.datasets.colmap import import_colmap
from tacsplat.datasets.inspect import format_summary, summarise
from tacsplat.datasets.reader import check_scene
from tacsplat.errors import InvalidInputError, SceneFormatError
from tacsplat.geometry import invert_pose, look_at

W, H = 32, 24
CAMERAS = {1: ("PINHOLE", [30.0, 31.0, 15.3, 12.4]), 2: ("SIMPLE_PINHOLE", [28.0, 16.2, 11.7])}
NUM_IMAGES, NUM_POINTS = 6, 40


def _write_model(root, num_points: int = NUM_POINTS, image_size=(W, H)):
    """A text model (``root/sparse/0``) of two cameras, six images on a ring around the origin and ``num_points``
    coloured points, each observed by every image it projects into; the images (``root/images``, of
    ``image_size``) are grey. Returns {image name: [(point index, (x, y))]} and the points' xyz and rgb."""
    model, images_dir = root / "sparse" / "0", root / "images"
    model.mkdir(parents=True)
    images_dir.mkdir(parents=True)
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-0.3, 0.3, (num_points, 3))
    rgb = rng.integers(0, 256, (num_points, 3))
    cameras = {
        cid: pycolmap.Camera(model=m, width=W, height=H, params=p, camera_id=cid) for cid, (m, p) in CAMERAS.items()
    }
    seen, tracks, image_lines = {}, {j: [] for j in range(num_points)}, []
    for iid in range(1, NUM_IMAGES + 1):
        name, cid = f"view_{iid:02d}.png", 1 + iid % 2
        a = 2 * np.pi * iid / NUM_IMAGES
        cam_from_world = invert_pose(look_at([2.0 * np.cos(a), 2.0 * np.sin(a), 0.4 + 0.1 * iid], [0.0, 0.0, 0.0]))
        local = xyz @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        pixels = cameras[cid].img_from_cam(local)
        inside = (local[:, 2] > 0) & (pixels[:, 0] >= 0) & (pixels[:, 0] < W) & (pixels[:, 1] >= 0)
        inside &= pixels[:, 1] < H
        seen[name] = [(int(j), pixels[j]) for j in np.flatnonzero(inside)]
        for k, (j, _) in enumerate(seen[name]):
            tracks[j].append(f"{iid} {k}")
        x, y, z, w = Rotation.from_matrix(cam_from_world[:3, :3]).as_quat()
        t = cam_from_world[:3, 3]
        image_lines.append(f"{iid} {_numbers([w, x, y, z, *t])} {cid} {name}")
        image_lines.append(" ".join(f"{_numbers(p)} {j + 1}" for j, p in seen[name]))
        cv2.imwrite(str(images_dir / name), np.full((image_size[1], image_size[0], 3), 90 + 20 * iid, np.uint8))
    (model / "cameras.txt").write_text("".join(f"{cid} {m} {W} {H} {_numbers(p)}\n" for cid, (m, p) in CAMERAS.items()))
    (model / "images.txt").write_text("\n".join(image_lines) + "\n")
    (model / "points3D.txt").write_text(
        "".join(
            f"{j + 1} {_numbers(xyz[j])} {' '.join(map(str, rgb[j]))} 0.5 {' '.join(tracks[j])}\n"
            for j in range(num_points)
        )
    )
    return seen, xyz, rgb


def _numbers(values) -> str:
    """Numbers as COLMAP's text files hold them (every digit of a float64)."""
    return " ".join(repr(float(v)) for v in values)


def _project(frame, point: np.ndarray) -> np.ndarray:
    """The pixel (x, y) of a world point in a scene frame (OpenCV, pixel centres at +0.5)."""
    local = invert_pose(frame.T_world_cam) @ np.append(point, 1.0)
    return (frame.intrinsics.K @ local[:3])[:2] / local[2]


@pytest.mark.parametrize("kind", ["text", "binary"])
def test_the_models_points_are_kept_in_the_scenes_world_and_project_onto_their_observations(tmp_path, kind):
    seen, xyz, rgb = _write_model(tmp_path / "m")
    model = tmp_path / "m" / "sparse" / "0"
    if kind == "binary":
        model = tmp_path / "m" / "bin"
        model.mkdir()
        pycolmap.Reconstruction(str(tmp_path / "m" / "sparse" / "0")).write_binary(str(model))
    out = import_colmap(model, tmp_path / "m" / "images", tmp_path / "scene", test_every=3, scale=0.25)

    assert json.loads((out / "scene.json").read_text())["sparse_points"] == "points3D.ply"
    scene = Scene.load(out)
    assert scene.sparse_points_path == out / "points3D.ply"
    points, colors = scene.sparse_points()
    assert points.shape == (NUM_POINTS, 3) and colors.dtype == np.uint8
    # the model's point j is the scene's point row[j] (a binary model need not list its points in id order)
    row = [int(np.argmin(np.abs(points - 0.25 * p).sum(axis=1))) for p in xyz]
    assert sorted(row) == list(range(NUM_POINTS))
    np.testing.assert_allclose(points[row], 0.25 * xyz, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(colors[row], rgb)
    names = json.loads((out / "scene.json").read_text())["extra"]["colmap_names"]
    frames = dict(zip(names, scene.frames))
    observations = 0
    for name, pixels in seen.items():
        for j, xy in pixels:
            np.testing.assert_allclose(_project(frames[name], points[row[j]]), xy, atol=1e-7)
            observations += 1
    assert observations > NUM_POINTS  # (the points are seen from several views)


def test_a_downscaled_image_folder_scales_its_cameras_and_the_points_still_project_onto_its_pixels(tmp_path, caplog):
    """Mip-NeRF 360's images_2 beside a full-size model: 16x12 images of 32x24 cameras."""
    seen, _, _ = _write_model(tmp_path / "m", image_size=(W // 2, H // 2))
    with caplog.at_level(logging.INFO, logger="tacsplat.datasets.colmap"):
        out = import_colmap(tmp_path / "m" / "sparse" / "0", tmp_path / "m" / "images", tmp_path / "scene")
    lines = [r.getMessage() for r in caplog.records if "1/2" in r.getMessage()]
    assert len(lines) == 2 and all("32x24" in line and "16x12" in line for line in lines)  # one per camera
    scene = Scene.load(out)
    names = json.loads((out / "scene.json").read_text())["extra"]["colmap_names"]
    for name, frame in zip(names, scene.frames):
        cid = 1 + int(name[5:7]) % 2
        K = pycolmap.Camera(model=CAMERAS[cid][0], width=W, height=H, params=CAMERAS[cid][1]).calibration_matrix()
        assert (frame.intrinsics.width, frame.intrinsics.height) == (16, 12)
        np.testing.assert_allclose(frame.intrinsics.K, np.diag([0.5, 0.5, 1.0]) @ K, rtol=0, atol=1e-12)
    points, _ = scene.sparse_points()
    frames = dict(zip(names, scene.frames))
    for name, pixels in seen.items():
        for j, xy in pixels:
            np.testing.assert_allclose(_project(frames[name], points[j]), 0.5 * np.asarray(xy), atol=1e-7)


@pytest.mark.parametrize(
    "names, w, h",
    [
        (("view_01.png", "view_03.png", "view_05.png"), 20, 15),  # all of camera 2's at 1/1.6: no whole factor
        (("view_01.png", "view_03.png", "view_05.png"), 16, 8),  # 1/2 across, 1/3 down
        (("view_01.png",), 16, 12),  # one image of camera 2 at 1/2, its others full size
    ],
)
def test_images_that_are_no_downscale_of_their_camera_are_refused_as_before(tmp_path, names, w, h):
    _write_model(tmp_path / "m")
    for name in names:
        cv2.imwrite(str(tmp_path / "m" / "images" / name), np.zeros((h, w, 3), np.uint8))
    with pytest.raises(SceneFormatError, match=rf"image is {w}x{h}, but camera 2 is 32x24") as info:
        import_colmap(tmp_path / "m" / "sparse" / "0", tmp_path / "m" / "images", tmp_path / "scene")
    assert info.value.path.name == "view_01.png"
    assert not (tmp_path / "scene").exists()


def test_a_folder_above_the_model_is_refused_with_a_hint_naming_the_model_below(tmp_path):
    _write_model(tmp_path / "m")
    (tmp_path / "m" / "sparse" / "10").mkdir()
    for name in ("cameras", "images", "points3D"):
        (tmp_path / "m" / "sparse" / "10" / f"{name}.txt").write_bytes(
            (tmp_path / "m" / "sparse" / "0" / f"{name}.txt").read_bytes()
        )
    (tmp_path / "m" / "sparse" / "notes").mkdir()
    with pytest.raises(SceneFormatError, match="not a readable COLMAP sparse model") as info:
        import_colmap(tmp_path / "m" / "sparse", tmp_path / "m" / "images", tmp_path / "scene")
    assert f"its subfolder {tmp_path / 'm' / 'sparse' / '0'} holds one: pass it (or " in str(info.value)
    assert str(info.value).endswith(f"(or {tmp_path / 'm' / 'sparse' / '10'})")
    with pytest.raises(SceneFormatError) as info:  # no model below: the message as it was
        import_colmap(tmp_path / "m" / "images", tmp_path / "m" / "images", tmp_path / "scene")
    assert str(info.value).endswith("expected cameras, images and points3D as .bin or .txt files")


def test_a_model_without_points_and_an_older_scene_have_no_sparse_points(tmp_path):
    _write_model(tmp_path / "m", num_points=0)
    out = import_colmap(tmp_path / "m" / "sparse" / "0", tmp_path / "m" / "images", tmp_path / "scene")
    assert "sparse_points" not in json.loads((out / "scene.json").read_text())
    assert not (out / "points3D.ply").exists()
    scene = Scene.load(out)
    assert scene.sparse_points_file is None and scene.sparse_points() is None


def test_a_damaged_or_missing_points_file_is_one_error_naming_it(tmp_path):
    _write_model(tmp_path / "m")
    out = import_colmap(tmp_path / "m" / "sparse" / "0", tmp_path / "m" / "images", tmp_path / "scene")
    ply = out / "points3D.ply"
    data = ply.read_bytes()
    ply.write_bytes(data[: len(data) - 100])  # truncated
    with pytest.raises(SceneFormatError, match="unreadable PLY") as info:
        Scene.load(out)
    assert info.value.path == ply and info.value.field == "sparse_points"
    scene, errors = check_scene(out)
    assert [e.path for e in errors] == [ply] and scene.sparse_points_file is None
    ply.unlink()
    with pytest.raises(SceneFormatError, match="sparse points file missing") as info:
        Scene.load(out)
    assert info.value.path == ply


def test_the_writer_refuses_sparse_points_that_are_none(tmp_path):
    _write_model(tmp_path / "m")
    out = import_colmap(tmp_path / "m" / "sparse" / "0", tmp_path / "m" / "images", tmp_path / "scene")
    with SceneWriter.resume(out) as writer:
        with pytest.raises(InvalidInputError, match="not finite"):
            writer.set_sparse_points(np.array([[0.0, np.nan, 1.0]]), np.zeros((1, 3), np.uint8))
        with pytest.raises(InvalidInputError, match="uint8 colours"):
            writer.set_sparse_points(np.zeros((2, 3)), np.zeros((2, 3)))
    assert len(Scene.load(out).sparse_points()[0]) == NUM_POINTS


def test_inspect_counts_the_sparse_points_and_a_copy_keeps_them(tmp_path):
    _write_model(tmp_path / "m")
    out = import_colmap(tmp_path / "m" / "sparse" / "0", tmp_path / "m" / "images", tmp_path / "scene")
    summary = summarise(out)
    assert summary["sparse_points"] == NUM_POINTS
    assert f"points    {NUM_POINTS} sparse points (points3D.ply)" in format_summary(summary)
    copy = copy_scene(out, tmp_path / "copy")  # as simulate-touches copies a scene before adding touches
    points, colors = Scene.load(copy).sparse_points()
    np.testing.assert_array_equal(points, Scene.load(out).sparse_points()[0])
    np.testing.assert_array_equal(colors, Scene.load(out).sparse_points()[1])
