"""Training and test views as tensors: cameras, the backdrop behind the object, compositing over it."""

from __future__ import annotations

import dataclasses
import logging

import cv2
import numpy as np
import torch

from tacsplat.errors import InvalidInputError
from tacsplat.geometry import invert_pose, pixel_centres
from tacsplat.types import CameraIntrinsics

log = logging.getLogger(__name__)


def camera_tensors(frames: list) -> tuple[torch.Tensor, torch.Tensor]:
    """World-to-camera matrices [C, 4, 4] and intrinsics [C, 3, 3] (float32) of scene frames."""
    viewmats = torch.tensor(np.stack([invert_pose(f.T_world_cam) for f in frames]), dtype=torch.float32)
    Ks = torch.tensor(np.stack([f.intrinsics.K for f in frames]), dtype=torch.float32)
    return viewmats, Ks


def fit_backdrop(
    image: np.ndarray, degree: int = 2, max_residual: float = 0.02, min_share: float = 0.5
) -> np.ndarray | None:
    """A smooth backdrop [H, W, 3] fitted to an image's [H, W, 3] two-pixel border, or None.

    A polynomial of ``degree`` in the pixel coordinates models a studio
    backdrop or a sky gradient. Where the fit to the whole border is not that
    smooth (RMS residual above ``max_residual``), the object may cross one
    edge (a close view): the fit is then made again on the border pixels
    within ``max_residual`` of a robust fit in every channel, and None when
    they are less than ``min_share`` of the border, or the pixels left out lie
    on more than one edge's strip (a cluttered real scene, or an object over a
    corner: a polynomial fits each edge apart, so a mix of object and backdrop
    would pass).
    """
    h, w = image.shape[:2]
    v, u = np.meshgrid(np.linspace(-1, 1, h), np.linspace(-1, 1, w), indexing="ij")
    basis = np.stack([u**i * v**j for i in range(degree + 1) for j in range(degree + 1 - i)], axis=-1)  # [H, W, B]
    border = np.zeros((h, w), bool)
    border[:2], border[-2:], border[:, :2], border[:, -2:] = True, True, True, True
    A, b = basis[border], image[border]  # [N, B], [N, 3]
    coeffs, *_ = np.linalg.lstsq(A, b, rcond=None)
    if np.sqrt(np.mean((A @ coeffs - b) ** 2)) > max_residual:
        for _ in range(5):  # least trimmed squares: refit to the half of the border the last fit explains best
            error = np.abs(A @ coeffs - b).max(axis=-1)
            best = error <= np.median(error)
            coeffs, *_ = np.linalg.lstsq(A[best], b[best], rcond=None)
        backdrop = np.abs(A @ coeffs - b).max(axis=-1) < max_residual  # (the refit's RMS on them is below that too)
        rows, cols = np.nonzero(border)
        edges = np.stack([rows < 2, rows >= h - 2, cols < 2, cols >= w - 2])  # [4, N]: each edge's 2-pixel strip
        one_edge = edges[:, ~backdrop].all(axis=1).any()  # every pixel left out on one edge's strip
        if backdrop.mean() < min_share or not one_edge:
            return None
        coeffs, *_ = np.linalg.lstsq(A[backdrop], b[backdrop], rcond=None)
    return np.clip(basis @ coeffs, 0.0, 1.0).astype(np.float32)


def known_backdrop(image: np.ndarray, color: tuple[float, float, float] | None = None) -> np.ndarray | None:
    """The backdrop behind the object in one view [H, W, 3] float32: ``color``, else fitted, else None."""
    h, w = image.shape[:2]
    if color is not None:
        return np.broadcast_to(np.asarray(color, dtype=np.float32), (h, w, 3)).copy()
    return fit_backdrop(image)


def over_black(backdrop: np.ndarray | None, image: np.ndarray) -> np.ndarray:
    """``backdrop`` [H, W, 3], or black of ``image``'s size where it is None (no known backdrop)."""
    return np.zeros((*image.shape[:2], 3), np.float32) if backdrop is None else backdrop


def background_image(image: np.ndarray, color: tuple[float, float, float] | None = None) -> np.ndarray:
    """The backdrop behind the object in one view [H, W, 3] float32: :func:`known_backdrop`, else black."""
    return over_black(known_backdrop(image, color), image)


def warn_no_backdrop(what: str, paths: list) -> None:
    """One warning naming the images in ``paths`` of ``what`` views ("training" or "test"), which have no backdrop."""
    if paths:
        shown = ", ".join(map(str, paths[:5])) + (f" and {len(paths) - 5} more" if len(paths) > 5 else "")
        unused = ", with no silhouette for the visual hull and no backdrop loss" if what == "training" else ""
        message = "%s images whose border is not a smooth backdrop: %s; rendered over black%s (--background sets one)"
        log.warning(message, what, shown, unused)


def training_frames(scene, train_views: int | None) -> list:
    """The training views a run uses: the scene's first ``train_views`` (all of them when None)."""
    train = scene.split("train")
    return train if train_views is None else train[:train_views]


def mesh_depth(mesh, frame) -> np.ndarray:
    """z-depth [H, W] of a trimesh mesh seen from a frame (0 where no surface), by ray casting."""
    intr = frame.intrinsics
    u, v = pixel_centres(intr.height, intr.width)
    dirs_cam = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
    R, t = frame.T_world_cam[:3, :3], frame.T_world_cam[:3, 3]
    origins = np.broadcast_to(t, dirs_cam.shape)
    hits, rays, _ = mesh.ray.intersects_location(origins, dirs_cam @ R.T, multiple_hits=False)
    depth = np.zeros(len(dirs_cam), dtype=np.float64)
    depth[rays] = (hits - t) @ R[:, 2]
    return depth.reshape(intr.height, intr.width).astype(np.float32)


class ScaledScene:
    """A scene seen at 1/``factor`` of its image size: what training and evaluation read with ``downscale``.

    Images are area-averaged (``cv2.INTER_AREA``) to ``(W // factor, H // factor)``; each frame's
    intrinsics are scaled by the exact size ratio per axis (``new / old``), which with pixel centres
    at +0.5 maps every image point ``(u, v)`` to ``(u * sx, v * sy)``. Ground-truth depth is ray cast
    from the ground-truth mesh at the new size when the scene has one (exact), else resampled at the
    nearest pixel. Everything else (touches, bounds, paths) is the scene's own.
    """

    def __init__(self, scene, factor: int):
        if not (isinstance(factor, int) and factor >= 1):
            raise InvalidInputError(f"downscale: must be an integer >= 1, got {factor!r}")
        self.base, self.factor = scene, factor
        self.frames = [self._scaled_frame(f) for f in scene.frames]
        self._by_id = {f.id: f for f in scene.frames}
        self._mesh = None

    def _scaled_frame(self, frame):
        intr = frame.intrinsics
        width, height = max(intr.width // self.factor, 1), max(intr.height // self.factor, 1)
        K = np.diag([width / intr.width, height / intr.height, 1.0]) @ intr.K
        return dataclasses.replace(frame, intrinsics=CameraIntrinsics(K, width, height))

    def __getattr__(self, name):  # touches, touch_points, bounds, path, meta, ...: the scene's own
        return getattr(self.base, name)

    def split(self, name: str) -> list:
        return [f for f in self.frames if f.split == name]

    def load_image(self, frame) -> np.ndarray:
        return _resized(self.base.load_image(self._by_id[frame.id]), frame, cv2.INTER_AREA)

    def gt_depth(self, frame) -> np.ndarray | None:
        mesh_path = self.base.gt_mesh_path
        if mesh_path is not None and mesh_path.is_file():
            if self._mesh is None:
                import trimesh

                self._mesh = trimesh.load(str(mesh_path), force="mesh")
            return mesh_depth(self._mesh, frame)
        return _resized(self.base.gt_depth(self._by_id[frame.id]), frame, cv2.INTER_NEAREST)

    def gt_normal(self, frame) -> np.ndarray | None:
        """The scene's ground-truth normals resampled at the nearest pixel, as :meth:`gt_depth` without a mesh."""
        return _resized(self.base.gt_normal(self._by_id[frame.id]), frame, cv2.INTER_NEAREST)


def _resized(image: np.ndarray | None, frame, interpolation: int) -> np.ndarray | None:
    """``image`` resampled to ``frame``'s size (None stays None)."""
    size = (frame.intrinsics.width, frame.intrinsics.height)
    return None if image is None else cv2.resize(image, size, interpolation=interpolation)


def scene_at(scene, downscale: int):
    """``scene`` itself, or a :class:`ScaledScene` of it when ``downscale`` > 1."""
    return scene if downscale == 1 else ScaledScene(scene, downscale)
