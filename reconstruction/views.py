"""Training and test views as tensors: cameras, the backdrop behind the object, compositing over it."""

from __future__ import annotations

import numpy as np
import torch

from tacsplat.geometry import invert_pose


def camera_tensors(frames: list) -> tuple[torch.Tensor, torch.Tensor]:
    """World-to-camera matrices [C, 4, 4] and intrinsics [C, 3, 3] (float32) of scene frames."""
    viewmats = torch.tensor(np.stack([invert_pose(f.T_world_cam) for f in frames]), dtype=torch.float32)
    Ks = torch.tensor(np.stack([f.intrinsics.K for f in frames]), dtype=torch.float32)
    return viewmats, Ks


def fit_backdrop(image: np.ndarray, degree: int = 2, max_residual: float = 0.02) -> np.ndarray | None:
    """A smooth backdrop [H, W, 3] fitted to an image's [H, W, 3] two-pixel border, or None.

    A polynomial of ``degree`` in the pixel coordinates models a studio
    backdrop or a sky gradient; None when the border is not that smooth (RMS
    residual above ``max_residual``), e.g. a cluttered real scene.
    """
    h, w = image.shape[:2]
    v, u = np.meshgrid(np.linspace(-1, 1, h), np.linspace(-1, 1, w), indexing="ij")
    basis = np.stack([u**i * v**j for i in range(degree + 1) for j in range(degree + 1 - i)], axis=-1)  # [H, W, B]
    border = np.zeros((h, w), bool)
    border[:2], border[-2:], border[:, :2], border[:, -2:] = True, True, True, True
    coeffs, *_ = np.linalg.lstsq(basis[border], image[border], rcond=None)
    residual = np.sqrt(np.mean((basis[border] @ coeffs - image[border]) ** 2))
    if residual > max_residual:
        return None
    return np.clip(basis @ coeffs, 0.0, 1.0).astype(np.float32)


def background_image(image: np.ndarray, colour: tuple[float, float, float] | None = None) -> np.ndarray:
    """The backdrop behind the object in one view [H, W, 3] float32: ``colour``, else fitted, else black."""
    h, w = image.shape[:2]
    if colour is not None:
        return np.broadcast_to(np.asarray(colour, dtype=np.float32), (h, w, 3)).copy()
    fitted = fit_backdrop(image)
    return np.zeros((h, w, 3), np.float32) if fitted is None else fitted


def composite(colors: torch.Tensor, alphas: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Over-composite renders [..., H, W, 3] made without background onto a background [H, W, 3]."""
    return colors + (1.0 - alphas) * background
