"""Import one object of NeRO's Glossy Synthetic dataset (the paper's Tables 1 and 2) into a scene directory.

The layout, as NeRO's own loader reads it (``dataset/database.py``,
``GlossySyntheticDatabase``), one folder per object (``GlossySynthetic/bell``):

- ``N.png``: the image of view ``N`` (``0``, ``1``, ...); its colour channels
  are used (NeRO drops any alpha);
- ``N-camera.pkl``: a pickled ``(pose, K)``, ``pose`` the 3x4 world-to-camera
  matrix in OpenCV axes (x right, y down, z forward) and ``K`` the 3x3
  intrinsics;
- ``N-depth.png``: 16-bit z-depth, ``value / 65535 * 15`` dataset units; the
  object is where that depth is below 14.5 (the rest is background);
- ``eval_pts.ply``: the ground-truth points on the object that NeRO's Chamfer
  distance uses; when it is missing, NeRO builds them from its test views'
  object depth, voxel-downsampled at 0.01 units, and so does this importer.

The split is NeRO's ``configs/synthetic_split_128.pkl`` (a pickled
``[test_ids, train_ids]``: 32 and 96 view names), from ``--split`` or found in
the object folder or its parent. Each view's colour is composited onto a
background colour outside the object's depth mask (the paper's official code,
``data_making/nero_to_refnerf.py``, does the same onto black). The test views'
depth becomes their ``gt/`` depth (``cd``) and the points the scene's
ground-truth points (``cd_paper``). ``K`` is kept as it is: pixel centres at
``+0.5``, as the scene format has them (NeRO back-projects its depth at integer
pixel coordinates, half a pixel off).

The pickles are read with an unpickler that builds numpy arrays and nothing
else: a dataset file cannot run code.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path

import numpy as np

from tacsplat.errors import SceneFormatError
from tacsplat.geometry import invert_pose, rigidity_problem, unproject_depth
from tacsplat.progress import progress_bar
from tacsplat.types import CameraIntrinsics

from .blender import check_options, composite, read_raw, read_rgba
from .reader import STRICT, load_points_ply
from .records import camera_problem, pose_problem
from .writer import new_import

SPLIT_FILE = "synthetic_split_128.pkl"
DEPTH_RANGE = 15.0  # dataset units at the depth PNG's 65535
BACKGROUND_DEPTH = 14.5  # dataset units: deeper is background
EVAL_VOXEL = 0.01  # dataset units: NeRO's downsampling of its fallback ground-truth points

# (module, name) an array pickle may construct; numpy's core module is numpy.core before numpy 2, numpy._core after
_ALLOWED = {("numpy", "ndarray"), ("numpy", "dtype"), ("builtins", "slice")} | {
    (f"numpy.{core}.{module}", name)
    for core in ("core", "_core")
    for module, name in (("multiarray", "_reconstruct"), ("multiarray", "scalar"), ("numeric", "_frombuffer"))
}


class _ArrayUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        if (module, name) not in _ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} (only numpy arrays are expected)")
        return super().find_class(module, name)


def load_array_pickle(path: Path, what: str):
    """The object in a pickle of numpy arrays, lists and tuples; a SceneFormatError naming ``path`` otherwise."""
    if not path.is_file():
        raise SceneFormatError(path, None, f"missing {what} (no such file)")
    try:
        return _ArrayUnpickler(io.BytesIO(path.read_bytes()), encoding="latin1").load()
    except Exception as exc:  # pickle raises many types for damaged or foreign bytes
        raise SceneFormatError(path, None, f"not a pickle of numpy arrays ({what}): {exc}") from exc


def read_camera(path: Path, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(T_world_cam [4, 4] OpenCV camera-to-world, K [3, 3])`` of an ``N-camera.pkl`` whose image is ``size``
    (w, h) pixels, the pose re-orthonormalised when off by rounding only; a SceneFormatError naming the file
    unless the pose and ``K`` are what the scene format holds (the writer's checks, ``records.pose_problem`` and
    ``records.camera_problem``)."""
    data = load_array_pickle(path, "camera")
    try:
        pose, K = (np.asarray(a, dtype=np.float64) for a in data)
    except (TypeError, ValueError, OverflowError):
        raise SceneFormatError(path, None, "expected a pickled (pose, K) pair of arrays") from None
    if pose.shape != (3, 4) or K.shape != (3, 3):
        raise SceneFormatError(path, None, f"expected a 3x4 pose and a 3x3 K, got {pose.shape} and {K.shape}")
    world_to_camera = np.vstack([pose, [0.0, 0.0, 0.0, 1.0]])
    if problem := rigidity_problem(world_to_camera, atol=1e-4):
        raise SceneFormatError(path, "pose", f"not a rigid transform: {problem}")
    U, _, Vt = np.linalg.svd(world_to_camera[:3, :3])  # off by a few digits' rounding: made exactly rigid
    world_to_camera[:3, :3] = U @ Vt
    T_world_cam = invert_pose(world_to_camera)
    if problem := pose_problem(T_world_cam):
        raise SceneFormatError(path, "pose", problem)
    if not (K[0, 1] == 0 and K[1, 0] == 0 and np.array_equal(K[2], [0.0, 0.0, 1.0])):
        raise SceneFormatError(path, "K", f"not a zero-skew pinhole camera matrix: {K.tolist()}")
    if problem := camera_problem(*(float(K[i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2))), *size):
        key, why = problem
        entry = {"fl_x": "K[0][0]", "fl_y": "K[1][1]", "cx": "K[0][2]", "cy": "K[1][2]"}.get(key, key)
        raise SceneFormatError(path, "K", f"{entry} ({key}) of a {size[0]}x{size[1]} px image: {why}")
    return T_world_cam, K


def read_depth(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """Z-depth [H, W] in dataset units of an ``N-depth.png``, 0 on the background (:data:`BACKGROUND_DEPTH`)."""
    raw = read_raw(path, None, "depth map", shape[::-1], "its image")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise SceneFormatError(path, None, f"expected a 16-bit grey depth map, got {raw.dtype} {raw.shape}")
    depth = raw.astype(np.float64) / 65535.0 * DEPTH_RANGE
    return np.where(depth < BACKGROUND_DEPTH, depth, 0.0)


def find_split(src: Path, split: Path | None) -> Path:
    """The split file: ``split``, else :data:`SPLIT_FILE` in ``src`` or its parent."""
    if split is not None:
        return split
    for folder in (src, src.parent):
        if (folder / SPLIT_FILE).is_file():
            return folder / SPLIT_FILE
    raise SceneFormatError(
        src / SPLIT_FILE,
        None,
        "missing: give NeRO's configs/synthetic_split_128.pkl with --split (or put it in the dataset folder)",
    )


def read_split(path: Path, names: set[str]) -> tuple[list[str], list[str]]:
    """``(train, test)`` view names of a split file, each sorted by number; every name must be a view of ``names``."""
    data = load_array_pickle(path, "split")
    try:
        test, train = ([str(n) for n in np.asarray(ids).ravel()] for ids in data)
    except (TypeError, ValueError):
        raise SceneFormatError(path, None, "expected a pickled [test ids, train ids]") from None
    if not train or not test or set(train) & set(test):
        raise SceneFormatError(path, None, f"expected two disjoint, non-empty lists; got {len(test)} and {len(train)}")
    if unknown := sorted((set(train) | set(test)) - names, key=_number):
        raise SceneFormatError(path, None, f"names views the dataset does not have: {', '.join(unknown[:5])}")
    return sorted(train, key=_number), sorted(test, key=_number)


def _number(name: str) -> tuple[int, str]:
    return (int(name), name) if name.isdigit() else (1 << 62, name)


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point per occupied voxel of side ``voxel``: the mean of its points."""
    keys = np.floor(points / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse.ravel(), points)
    return sums / counts[:, None]


def import_nero(src, out, split: Path | None = None, background_rgb=(255, 255, 255), scale: float = 1.0) -> Path:
    """Convert one Glossy Synthetic object folder ``src`` into a scene directory ``out`` (module docstring).

    ``scale`` (metres per dataset unit) multiplies the camera positions, depths and points. ``out`` is claimed as
    the ``--out`` of a writing command (``datasets.outputs``). Returns ``out``.
    """

    src, out = Path(src), Path(out)
    check_options(scale)
    if not src.is_dir():
        raise SceneFormatError(src, None, "not a folder (expected a Glossy Synthetic object folder, e.g. .../bell)")
    if not (names := {p.name.removesuffix("-camera.pkl") for p in src.glob("*-camera.pkl")}):
        raise SceneFormatError(src, None, "no N-camera.pkl files: not a Glossy Synthetic object folder")
    split_path = find_split(src, split)
    train, test = read_split(split_path, names)

    first_image = src / f"{train[0]}.png"
    height, width = read_rgba(first_image).shape[:2]
    cameras = {name: read_camera(src / f"{name}-camera.pkl", (width, height)) for name in train + test}
    eval_points = src / "eval_pts.ply"
    fallback_points = []
    with (
        new_import(
            out,
            CameraIntrinsics(cameras[train[0]][1], width, height),
            "nero",
            src,
            None,
            split_file=str(split_path.resolve()),
            background_rgb=list(background_rgb),
            scale=scale,
            ground_truth="eval_pts.ply" if eval_points.is_file() else f"test views' depth, {EVAL_VOXEL} voxels",
        ) as writer,
        progress_bar(total=len(train) + len(test), desc=f"import {src.name}", unit="view") as progress,
    ):
        for split_name, views in (("train", train), ("test", test)):
            for name in views:
                unit_pose, K = cameras[name]
                rgb = read_rgba(src / f"{name}.png", None, (width, height), first_image.name)[:, :, :3]
                depth = read_depth(src / f"{name}-depth.png", (height, width))
                pose = unit_pose.copy()
                pose[:3, 3] *= scale
                gt_depth = (scale * depth).astype(np.float32) if split_name == "test" else None
                rgba = np.concatenate([rgb, (depth > 0)[:, :, None].astype(np.float64)], axis=2)
                writer.add_frame(
                    composite(rgba, background_rgb), pose, split_name, gt_depth, CameraIntrinsics(K, width, height)
                )
                if split_name == "test" and not eval_points.is_file():
                    fallback_points.append(unproject_depth(depth, K, unit_pose))
                progress.update()
        if eval_points.is_file():  # checked as the reader checks the scene's copy
            points = load_points_ply(eval_points, STRICT, None)
        else:
            points = voxel_downsample(np.concatenate(fallback_points), EVAL_VOXEL)
        writer.set_gt_points(scale * points)
    return out
