"""Miniature copies of the paper's datasets, written file by file as they are distributed: Shiny Blender (Ref-NeRF:
transforms_*.json, RGBA r_N.png, 16-bit 4-channel r_N_disp.tiff, r_N_normal.png) and one object of Glossy Synthetic
(NeRO: N.png, pickled N-camera.pkl, 16-bit N-depth.png, eval_pts.ply, the split pickle). The object is a sphere of
radius ``RADIUS`` at the origin, so every depth is known in closed form."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import cv2
import numpy as np
import trimesh

from tacsplat.geometry import focal_from_fov, invert_pose, look_at, opencv_to_opengl, pixel_centres

RADIUS = 1.0
SIZE = 24  # pixels, square
ANGLE_X = 0.6911112070083618  # NeRF synthetic's camera_angle_x


def ring_pose(i: int, n: int, distance: float = 4.0) -> np.ndarray:
    """OpenCV camera-to-world pose ``i`` of ``n`` around the sphere, looking at its centre, at varied heights."""
    a = 2 * np.pi * i / n + 0.1
    height = distance * 0.5 * np.sin(1.7 * i + 0.3)
    return look_at([distance * np.cos(a), distance * np.sin(a), height], [0.0, 0.0, 0.0])


def sphere_depth(K: np.ndarray, T_world_cam: np.ndarray, size: int = SIZE) -> np.ndarray:
    """Z-depth [size, size] of the sphere through each pixel centre (``+0.5``), 0 where the ray misses it."""
    u, v = pixel_centres(size, size)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)  # z = 1
    d = rays @ T_world_cam[:3, :3].T  # [H, W, 3] world directions, unnormalised
    o = T_world_cam[:3, 3]
    a, b, c = (d * d).sum(-1), 2 * (d @ o), o @ o - RADIUS**2
    disc = b * b - 4 * a * c
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a)  # along d: the z-depth, since d's camera z is 1
    return np.where(disc > 0, t, 0.0)


def sphere_normals(K: np.ndarray, T_world_cam: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World-frame unit normals [H, W, 3] of the sphere where ``depth`` (:func:`sphere_depth`) has it, else 0."""
    from tacsplat.geometry import unproject_depth

    normal = np.zeros(depth.shape + (3,))
    points = unproject_depth(depth, K, T_world_cam)  # row-major over the pixels with depth
    normal[depth > 0] = points / np.linalg.norm(points, axis=1, keepdims=True)
    return normal


def shaded_rgb(depth: np.ndarray, seed: int) -> np.ndarray:
    """Some colour [H, W, 3] uint8 on the sphere (varied per view)."""
    rng = np.random.default_rng(seed)
    rgb = rng.integers(40, 220, size=depth.shape + (3,)).astype(np.uint8)
    return np.where((depth > 0)[..., None], rgb, 0).astype(np.uint8)


def make_shiny_blender(root: Path, n_train: int = 10, n_test: int = 3) -> Path:
    """A Shiny Blender object folder (``root/toaster``)."""
    src = root / "toaster"
    f = focal_from_fov(ANGLE_X, SIZE)
    K = np.array([[f, 0.0, SIZE / 2], [0.0, f, SIZE / 2], [0.0, 0.0, 1.0]])
    for split, n, offset in (("train", n_train, 0), ("test", n_test, 0.5)):
        (src / split).mkdir(parents=True)
        frames = []
        for k in range(n):
            pose = ring_pose(k + offset, n)
            depth = sphere_depth(K, pose)
            alpha = np.where(depth > 0, 255, 0).astype(np.uint8)
            rgba = np.concatenate([shaded_rgb(depth, 100 * k + n), alpha[..., None]], axis=-1)
            cv2.imwrite(str(src / split / f"r_{k}.png"), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
            disparity = np.where(depth > 0, 1.0 / (1.0 + depth), 0.0)
            d16 = np.rint(disparity * 65535).astype(np.uint16)
            tiff = np.stack([d16, d16, d16, np.where(depth > 0, 65535, 0).astype(np.uint16)], axis=-1)
            cv2.imwrite(str(src / split / f"r_{k}_disp.tiff"), tiff)
            normal = sphere_normals(K, pose, depth)  # world frame, as Blender writes it
            rgb = np.where((depth > 0)[..., None], np.rint((normal + 1) / 2 * 255), 0).astype(np.uint8)
            cv2.imwrite(str(src / split / f"r_{k}_normal.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": opencv_to_opengl(pose).tolist()})
        (src / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": ANGLE_X, "frames": frames}))
    return src


GLOSSY_K = np.array([[30.0, 0.0, SIZE / 2 + 0.7], [0.0, 31.0, SIZE / 2 - 0.4], [0.0, 0.0, 1.0]])


def make_glossy_synthetic(
    root: Path, views: int = 12, test: tuple[int, ...] = (0, 4, 2, 9), eval_points: bool = True
) -> Path:
    """A Glossy Synthetic object folder (``root/bell``) and NeRO's split pickle beside it (``root``): views 0 to
    ``views - 1``, ``test`` the test ids in NeRO's unsorted order, the rest train."""
    src = root / "bell"
    src.mkdir(parents=True)
    for k in range(views):
        pose = ring_pose(k, views, distance=3.0)
        depth = sphere_depth(GLOSSY_K, pose)
        rgb = np.where((depth > 0)[..., None], shaded_rgb(depth, k), 90).astype(np.uint8)  # a grey environment
        cv2.imwrite(str(src / f"{k}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        w2c = invert_pose(pose)[:3].astype(np.float32)
        (src / f"{k}-camera.pkl").write_bytes(pickle.dumps((w2c, GLOSSY_K.astype(np.float32))))
        stored = np.where(depth > 0, depth, 15.0)  # the background renders at the far distance
        cv2.imwrite(str(src / f"{k}-depth.png"), np.rint(stored / 15.0 * 65535).astype(np.uint16))
    if eval_points:  # evenly spread, as NeRO's voxel-downsampled points are: a Fibonacci sphere
        i = np.arange(3000) + 0.5
        z, a = 1 - 2 * i / 3000, np.pi * (1 + 5**0.5) * i
        points = RADIUS * np.stack([np.sqrt(1 - z**2) * np.cos(a), np.sqrt(1 - z**2) * np.sin(a), z], axis=1)
        trimesh.PointCloud(points).export(str(src / "eval_pts.ply"))
    test_ids = np.array([str(i) for i in test])
    train_ids = [str(i) for i in range(views) if i not in test]
    (root / "synthetic_split_128.pkl").write_bytes(pickle.dumps([test_ids, train_ids]))
    return src
