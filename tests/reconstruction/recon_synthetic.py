"""A tiny synthetic scene for the reconstruction tests: a textured sphere of known Gaussians.

Built with the reference rasterizer and written with the datasets writer: the
images are renders of the known Gaussians, the ground-truth depth is the
analytic sphere, and the touches are flat-gel indentations of the sphere.
"""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from tacsplat.datasets import SceneMeta, SceneWriter, SensorModel
from tacsplat.geometry import invert_pose, look_at, make_pose
from tacsplat.reconstruction.gaussians import quats_to_rotmats
from tacsplat.reconstruction.raster.rendering import rasterization
from tacsplat.types import CameraIntrinsics

RADIUS = 0.05  # metres, sphere centred at the origin
CAMERA_DISTANCE = 0.25


def sphere_gaussians(n: int = 400):
    """Flat textured Gaussians tiling the sphere: (means, quats, scales, opacities, colors) float64 tensors."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    normals = np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], axis=1)
    means = RADIUS * normals
    quats = []
    for nrm in normals:
        helper = np.array([1.0, 0, 0]) if abs(nrm[0]) < 0.9 else np.array([0, 1.0, 0])
        x = np.cross(helper, nrm)
        x /= np.linalg.norm(x)
        quats.append(
            Rotation.from_matrix(np.stack([x, np.cross(nrm, x), nrm], axis=1)).as_quat(
                canonical=True, scalar_first=True
            )
        )
    spacing = math.sqrt(4 * math.pi * RADIUS**2 / n)
    scales = np.tile([0.7 * spacing, 0.7 * spacing, 0.05 * spacing], (n, 1))
    colors = 0.5 + 0.4 * np.stack(
        [np.sin(40 * means[:, 0] + 1), np.sin(40 * means[:, 1] + 2), np.sin(40 * means[:, 2] + 3)], axis=1
    )
    t = lambda a: torch.tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    return t(means), t(np.array(quats)), t(scales), t(np.full(n, 0.95)), t(colors)


def precisions(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Inverse covariances [N, 3, 3] of Sigma = R S S^T R^T (paper Eq. 3), from activated scales [N, 3], as the
    matrix product: the oracle of the whitening and of the viewer's covariances (float64 in the tests)."""
    R = quats_to_rotmats(quats)
    return R @ torch.diag_embed(scales.pow(-2)) @ R.transpose(-1, -2)


def sphere_depth(K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int) -> np.ndarray:
    """Analytic z-depth [H, W] of the sphere (0 = background)."""
    v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    d_world = d_cam @ T_world_cam[:3, :3].T
    o = T_world_cam[:3, 3]
    a = (d_world**2).sum(-1)
    b = 2 * d_world @ o
    c = o @ o - RADIUS**2
    disc = b**2 - 4 * a * c
    t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0.0)
    return t.astype(np.float32)  # the ray's parameter is the z-depth because d_cam has z = 1


def touch_reading(normal: np.ndarray, sensor: SensorModel, press: float) -> tuple[np.ndarray, np.ndarray]:
    """(depth [h, w], T_world_sensor) of a flat gel pressed ``press`` metres into the sphere along -normal."""
    n = normal / np.linalg.norm(normal)
    helper = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    ex = np.cross(helper, n)
    ex /= np.linalg.norm(ex)
    ey = np.cross(-n, ex)  # right-handed frame with z = -n (the gel's normal points at the object)
    T_world_sensor = make_pose(np.stack([ex, ey, -n], axis=1), (RADIUS - press) * n)
    h, w = sensor.height_px, sensor.width_px
    y, x = np.meshgrid(
        (np.arange(h) + 0.5 - h / 2) * sensor.pixel_size_m,
        (np.arange(w) + 0.5 - w / 2) * sensor.pixel_size_m,
        indexing="ij",
    )
    r2 = x**2 + y**2
    depth = press - (RADIUS - np.sqrt(np.maximum(RADIUS**2 - r2, 0)))
    return np.maximum(depth, 0).astype(np.float32), T_world_sensor


def backdrop_gradient(size: int) -> np.ndarray:
    """A smooth studio backdrop [size, size, 3]: a quadratic in the pixel coordinates, darker at the top."""
    v, u = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size), indexing="ij")
    return (0.3 + 0.3 * v + 0.1 * u * v)[..., None] * np.array([1.0, 0.95, 0.9])


def build_sphere_scene(
    path: Path,
    size: int = 48,
    train_views: int = 6,
    test_views: int = 2,
    touches: bool = True,
    seed: int = 0,
    backdrop: bool = False,
    centre_row: float = 0.5,
) -> Path:
    """Write the synthetic sphere scene to ``path``; returns it. ``backdrop``: the sphere in front of
    :func:`backdrop_gradient` (else black); ``centre_row``: the principal point's row as a share of the image's
    height (below about 0.25 the sphere crosses the top edge, as in a close view)."""
    rng = np.random.default_rng(seed)
    focal = size * 1.25
    K = np.array([[focal, 0, size / 2], [0, focal, size * centre_row], [0, 0, 1.0]])
    intr = CameraIntrinsics(K, size, size)
    sensor = SensorModel("synthetic-gel", 12, 12, 0.0006, 0.002)
    means, quats, scales, opacities, colors = sphere_gaussians()
    writer = SceneWriter.create(path, intr, SceneMeta("sim", "synthetic-sphere"), sensor if touches else None)
    with writer:
        total = train_views + test_views
        for k in range(total):
            azimuth = 2 * math.pi * k / total + 0.3 * rng.uniform()
            elevation = 0.6 * math.sin(2.1 * k)
            eye = CAMERA_DISTANCE * np.array(
                [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
            )
            T_world_cam = look_at(eye, np.zeros(3))
            viewmat = torch.tensor(invert_pose(T_world_cam))[None]
            image, alpha, _ = rasterization(
                means,
                quats,
                scales,
                opacities,
                colors,
                viewmat,
                torch.tensor(K)[None],
                size,
                size,
                backgrounds=torch.zeros(1, 3, dtype=torch.float64),
                backend="torch",
            )
            rgb = image[0].numpy() + (1 - alpha[0].numpy()) * (backdrop_gradient(size) if backdrop else 0.0)
            rgb = (np.clip(rgb, 0, 1) * 255).round().astype(np.uint8)
            split = "test" if test_views and k % (total // test_views) == total // test_views - 1 else "train"
            writer.add_frame(rgb, T_world_cam, split, gt_depth=sphere_depth(K, T_world_cam, size, size))
        if touches:
            for grasp in range(2):
                for finger in range(2):
                    normal = rng.normal(size=3)
                    depth, T_world_sensor = touch_reading(normal, sensor, 0.0008)
                    writer.add_touch(depth, T_world_sensor, grasp, f"finger{finger}")
    return path


def one_error_line(capsys, *words, prefix: str = "error: ") -> str:
    """The single stderr line of a refused command (no traceback), checked for ``words``; it starts with
    ``prefix`` (a usage error's starts with the command: ``prefix=""`` checks only that it holds "error: ")."""
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(prefix) and "error: " in lines[0] and "Traceback" not in err, err
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


def pause_training(monkeypatch) -> tuple[threading.Event, threading.Event]:
    """Make every training step wait: ``(in_training, finish)``, set by the first step as it starts, and to set
    for it (and every later one) to go on; a training started in a thread then holds its run folder meanwhile."""
    from tacsplat.reconstruction.trainer import Trainer

    in_training, finish = threading.Event(), threading.Event()
    real_step = Trainer.train_step

    def paused_step(self):
        in_training.set()
        assert finish.wait(120)
        return real_step(self)

    monkeypatch.setattr(Trainer, "train_step", paused_step)
    return in_training, finish
