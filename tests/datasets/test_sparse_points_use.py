"""A scene's sparse points (an import's SfM points, built from every image, held-out ones included) go only where
every image goes: a copy of some frames drops them, so a few-view comparison triangulates from its own views as it
did before imports kept their points; `bench paper --dataset`'s minimal setting is such a copy. And `import
nerfstudio` takes ns-process-data's points (``ply_file_path``) into the scene's world as it takes the poses."""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tacsplat.apps.paper_bench import DatasetSceneJob
from tacsplat.datasets import Scene, SceneWriter, copy_scene
from tacsplat.datasets.nerfstudio import import_nerfstudio
from tacsplat.errors import SceneFormatError
from tacsplat.geometry import invert_pose, look_at, opencv_to_opengl

sys.path.insert(0, str(Path(__file__).parents[1] / "reconstruction"))  # pytest's importlib mode does not add folders
from recon_synthetic import build_sphere_scene  # noqa: E402

TRAIN, TEST = 7, 2


@pytest.fixture
def scene(tmp_path) -> Scene:
    """The synthetic sphere scene (7 train views, 2 test views, touches) with 30 sparse points."""
    path = build_sphere_scene(tmp_path / "scene", size=16, train_views=TRAIN, test_views=TEST)
    rng = np.random.default_rng(0)
    with SceneWriter.resume(path) as writer:
        writer.set_sparse_points(rng.uniform(-0.1, 0.1, (30, 3)), rng.integers(0, 256, (30, 3), dtype=np.uint8))
    return Scene.load(path)


def test_a_copy_of_every_frame_keeps_the_sparse_points_and_a_copy_of_some_drops_them(tmp_path, scene):
    every = copy_scene(scene, tmp_path / "every", frames=scene.split("test") + scene.split("train"))
    np.testing.assert_array_equal(Scene.load(every).sparse_points()[0], scene.sparse_points()[0])
    np.testing.assert_array_equal(Scene.load(every).sparse_points()[1], scene.sparse_points()[1])

    some = Scene.load(copy_scene(scene, tmp_path / "some", frames=scene.split("train")[:2] + scene.split("test")))
    assert len(some.frames) == 2 + TEST
    assert some.sparse_points_file is None and some.sparse_points() is None
    assert not (some.path / "points3D.ply").exists()


@pytest.mark.parametrize("count, kept", [(5, False), (0, True)])  # the minimal setting's 5 views; full-views' all
def test_the_paper_benchs_copy_keeps_the_sparse_points_only_with_every_train_view(tmp_path, scene, count, kept):
    out = tmp_path / "bench" / "scene"
    out.parent.mkdir()
    summary = DatasetSceneJob(out=out, base=scene.path, count=count)()
    copy = Scene.load(out)
    assert len(summary["train_views"]) == len(copy.split("train")) == (count or TRAIN)
    assert (copy.sparse_points() is not None) == kept


# --- import nerfstudio: ply_file_path -----------------------------------------------------------------------------

W, H, F = 64, 48, 48.0
K = np.array([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])
# ns-process-data's applied_transform (world y and z swapped, then z negated), here with a shift too
APPLIED = np.array([[1.0, 0.0, 0.0, 0.3], [0.0, 0.0, 1.0, -0.2], [0.0, -1.0, 0.0, 0.1], [0.0, 0.0, 0.0, 1.0]])
APPLIED_SCALE, SCALE = 2.5, 0.5


def _pixels(pose: np.ndarray, xyz: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The pixel (column, row) each point [N, 3] falls in, seen from the OpenCV camera-to-world ``pose``."""
    local = (invert_pose(pose) @ np.c_[xyz, np.ones(len(xyz))].T)[:3]
    return np.floor((K @ local)[:2] / local[2]).T.astype(int)


def _write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray | None) -> None:
    """An ASCII PLY as ns-process-data's create_ply_from_colmap writes it (float x y z, uint8 red green blue)."""
    header = ["ply", "format ascii 1.0", f"element vertex {len(xyz)}"] + [f"property float {a}" for a in "xyz"]
    header += [] if rgb is None else [f"property uint8 {c}" for c in ("red", "green", "blue")]
    colors = [""] * len(xyz) if rgb is None else [" " + " ".join(map(str, c)) for c in rgb]
    rows = [" ".join(map(repr, map(float, p))) + c for p, c in zip(xyz, colors)]
    path.write_text("\n".join([*header, "end_header", *rows]) + "\n")


def _ns_dataset(root: Path, colors: bool = True) -> tuple[Path, np.ndarray, np.ndarray]:
    """ns-process-data's output for 4 views of 12 coloured points: each image shows each point as one pixel of its
    colour on black; poses and points saved as it saves them (applied_transform, then applied_scale). Returns the
    dataset folder and the points' original xyz and rgb."""
    rng = np.random.default_rng(4)
    xyz = rng.uniform(-0.3, 0.3, (12, 3))
    rgb = rng.integers(30, 256, (12, 3), dtype=np.uint8)
    frames = []
    for i in range(4):
        pose = look_at([2.0 * np.cos(1.3 * i), 2.0 * np.sin(1.3 * i), 0.6 + 0.1 * i], [0.0, 0.0, 0.0])
        image, pixels = np.zeros((H, W, 3), np.uint8), _pixels(pose, xyz, K)
        assert len(set(map(tuple, pixels))) == len(xyz) and (pixels >= 0).all() and (pixels < [W, H]).all()
        for (u, v), color in zip(pixels, rgb):
            image[v, u] = color
        (root / "images").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / f"images/frame_{i:05d}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        saved = APPLIED @ opencv_to_opengl(pose)
        saved[:3, 3] *= APPLIED_SCALE
        frames.append({"file_path": f"images/frame_{i:05d}.png", "transform_matrix": saved.tolist()})
    saved_xyz = APPLIED_SCALE * (xyz @ APPLIED[:3, :3].T + APPLIED[:3, 3])
    _write_ply(root / "sparse_pc.ply", saved_xyz, rgb if colors else None)
    data = {"w": W, "h": H, "fl_x": F, "fl_y": F, "cx": W / 2, "cy": H / 2, "camera_model": "PINHOLE"}
    data |= {"frames": frames, "applied_transform": APPLIED[:3].tolist(), "applied_scale": APPLIED_SCALE}
    (root / "transforms.json").write_text(json.dumps(data | {"ply_file_path": "sparse_pc.ply"}))
    return root, xyz, rgb


def test_import_nerfstudio_takes_the_ply_into_the_scenes_world_as_the_poses(tmp_path, caplog):
    src, xyz, rgb = _ns_dataset(tmp_path / "ns")
    with caplog.at_level(logging.WARNING):
        scene = Scene.load(import_nerfstudio(src, tmp_path / "scene", test_every=0, scale=SCALE))
    points, colors = scene.sparse_points()
    np.testing.assert_allclose(points, SCALE * xyz, atol=1e-6)
    np.testing.assert_array_equal(colors, rgb)
    for frame in scene.frames:  # each point lands on the pixel that shows it, in every imported view
        image = np.rint(scene.load_image(frame) * 255).astype(np.uint8)
        shown = np.array([image[v, u] for u, v in _pixels(frame.T_world_cam, points, frame.intrinsics.K)])
        np.testing.assert_array_equal(shown, rgb)
    assert "not imported" not in caplog.text
    assert "not_imported" not in json.loads((scene.path / "scene.json").read_text())["extra"]


def test_a_ply_without_colors_gives_mid_grey_points(tmp_path):
    src, xyz, _ = _ns_dataset(tmp_path / "ns", colors=False)
    points, colors = Scene.load(import_nerfstudio(src, tmp_path / "scene", scale=SCALE)).sparse_points()
    np.testing.assert_allclose(points, SCALE * xyz, atol=1e-6)
    assert (colors == 128).all() and colors.shape == (12, 3)


@pytest.mark.parametrize(
    "ply, why",
    [
        (None, "no such file"),
        (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend", "unreadable PLY"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
            b"end_header\n",
            "holds no points",
        ),
    ],
    ids=["missing", "unreadable", "empty"],
)
def test_a_missing_unreadable_or_empty_ply_is_said_and_left_out(tmp_path, caplog, ply, why):
    """As nerfstudio goes on without them (splatfacto then starts at random): training triangulates its own."""
    src, _, _ = _ns_dataset(tmp_path / "ns")
    (src / "sparse_pc.ply").unlink()
    if ply is not None:
        (src / "sparse_pc.ply").write_bytes(ply)
    with caplog.at_level(logging.WARNING):
        scene = Scene.load(import_nerfstudio(src, tmp_path / "scene", scale=SCALE))
    assert scene.sparse_points() is None
    assert f"{src / 'transforms.json'}: ply_file_path {src / 'sparse_pc.ply'}: {why}" in caplog.text
    assert json.loads((scene.path / "scene.json").read_text())["extra"]["not_imported"] == {
        "ply_file_path": "sparse_pc.ply"
    }


def test_a_ply_file_path_that_is_no_path_is_one_error(tmp_path):
    src, _, _ = _ns_dataset(tmp_path / "ns")
    data = json.loads((src / "transforms.json").read_text())
    (src / "transforms.json").write_text(json.dumps(data | {"ply_file_path": 3}))
    with pytest.raises(SceneFormatError, match="expected a path string, got 3") as info:
        import_nerfstudio(src, tmp_path / "scene")
    assert info.value.field == "ply_file_path"
    assert not (tmp_path / "scene").exists()
