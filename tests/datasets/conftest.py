"""Small scenes built on the fly for the datasets tests."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from tacsplat.datasets import SceneMeta, SceneWriter, SensorModel
from tacsplat.geometry import look_at
from tacsplat.types import CameraIntrinsics

WIDTH, HEIGHT = 16, 12
SENSOR = SensorModel(name="gel", width_px=10, height_px=8, pixel_size_m=5e-4, gel_thickness_m=2e-3)


def intrinsics(width: int = WIDTH, height: int = HEIGHT, f: float = 14.0) -> CameraIntrinsics:
    return CameraIntrinsics(
        np.array([[f, 0.0, width / 2], [0.0, f * 1.05, height / 2], [0.0, 0.0, 1.0]]), width, height
    )


def ring_pose(i: int, radius: float = 0.4) -> np.ndarray:
    """OpenCV camera-to-world pose on a ring around the origin, looking at it."""
    a = 2 * np.pi * i / 7 + 0.3
    return look_at([radius * np.cos(a), radius * np.sin(a), 0.15 + 0.02 * i], [0.0, 0.0, 0.0])


def frame_image(i: int, width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """A uint8 RGB image whose content encodes the frame number."""
    rng = np.random.default_rng(i)
    img = rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)
    img[0, 0] = [i % 251, (7 * i) % 251, 42]
    return img


def touch_depth(i: int, sensor: SensorModel = SENSOR) -> np.ndarray:
    """An indentation map whose contact patch encodes the touch number (every other touch misses)."""
    depth = np.zeros((sensor.height_px, sensor.width_px), np.float32)
    if i % 2 == 0:
        depth[2:5, 3:7] = 1e-4 * (i + 1)
    return depth


def touch_pose(i: int) -> np.ndarray:
    return look_at([0.05 * np.cos(i), 0.05 * np.sin(i), 0.03], [0.0, 0.0, 0.0])


def build_scene(path, n_frames: int = 4, n_touches: int = 4, sensor: SensorModel | None = SENSOR, gt: bool = True):
    """A valid scene: frames (every third one a test view with ground-truth depth) and touches, 2 per grasp."""
    meta = SceneMeta(source="sim", object="test-object", capture_plan={"views": n_frames})
    with SceneWriter.create(path, intrinsics(), meta, sensor) as writer:
        for i in range(n_frames):
            test = i % 3 == 1
            gt_depth = np.full((HEIGHT, WIDTH), 0.4 + 0.01 * i, np.float32) if (gt and test) else None
            writer.add_frame(frame_image(i), ring_pose(i), split="test" if test else "train", gt_depth=gt_depth)
        for i in range(n_touches):
            writer.add_touch(touch_depth(i), touch_pose(i), grasp=i // 2, finger=["index", "thumb"][i % 2])
    return path


@pytest.fixture(scope="session")
def _scene_template(tmp_path_factory):
    return build_scene(tmp_path_factory.mktemp("template") / "scene")


@pytest.fixture
def scene_dir(tmp_path, _scene_template):
    """A fresh copy of a valid 4-frame, 4-touch scene (built once: the writer fsyncs every file)."""
    return Path(shutil.copytree(_scene_template, tmp_path / "scene"))


@pytest.fixture
def h():
    """These helpers (test modules cannot import conftest under --import-mode=importlib)."""
    import sys

    return sys.modules[__name__]
