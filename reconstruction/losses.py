"""The training losses of tactile-informed 3DGS (paper Sec. 3-4): photometric, 3D transmittance, smoothness.

Equation numbers refer to ``paper/tactile-informed-3dgs.tex``: Eq. 1 is the
Gaussian influence f(x; Sigma, mu), Eq. 6 the average transmittance T(p),
Eq. 7 the transmittance loss L_T and Eq. 8 the edge-aware smoothness L_S.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

from tacsplat.errors import InvalidInputError
from tacsplat.geometry import project_points
from tacsplat.reconstruction.gaussians import precisions
from tacsplat.reconstruction.metrics import ssim_map


def photometric_loss(rendered: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2) -> torch.Tensor:
    """(1 - w) L1 + w D-SSIM of [H, W, 3] (or [B, H, W, 3]) images, w = 0.2 (Kerbl et al., paper Sec. 3)."""
    l1 = (rendered - target).abs().mean()
    d_ssim = 1.0 - ssim_map(rendered, target).mean()
    return (1.0 - ssim_weight) * l1 + ssim_weight * d_ssim


def backdrop_alpha_loss(alpha: torch.Tensor, backdrop_mask: torch.Tensor) -> torch.Tensor:
    """Mean rendered alpha [H, W] over the pixels [H, W] bool that show the bare backdrop.

    Not in the paper: with few views, opaque Gaussians coloured like a smooth
    backdrop explain the images as well as empty space does, and they become
    floaters in every other view; this keeps the backdrop transparent.
    """
    return (alpha * backdrop_mask).sum() / backdrop_mask.sum().clamp_min(1)


# --------------------------------------------------------------------------- transmittance


def gaussian_influence(
    points: torch.Tensor,  # [P, 3]
    means: torch.Tensor,  # [P, K, 3]
    precision: torch.Tensor,  # [P, K, 3, 3]
) -> torch.Tensor:
    """Eq. 1: f(p; Sigma, mu) = exp(-1/2 (p - mu)^T Sigma^-1 (p - mu)) for each point and its K Gaussians, [P, K]."""
    d = points[:, None, :] - means
    maha = torch.einsum("pki,pkij,pkj->pk", d, precision, d)
    return torch.exp(-0.5 * maha.clamp_min(0.0))


class TouchNeighbours:
    """Candidate G_t Gaussians near each touch point, from a k-d tree on detached means.

    The tree is rebuilt every ``rebuild_every`` calls (and after
    :meth:`invalidate`, which densification must call because it renumbers the
    Gaussians), so the neighbour search costs little per iteration; the
    influence itself is always evaluated with the live parameters.
    """

    def __init__(self, touch_points: np.ndarray, num_candidates: int, max_distance: float, rebuild_every: int):
        if num_candidates < 1 or rebuild_every < 1 or not max_distance > 0:
            raise InvalidInputError("TouchNeighbours: num_candidates, rebuild_every and max_distance must be positive")
        self.touch_points = np.asarray(touch_points, dtype=np.float64).reshape(-1, 3)
        self.num_candidates = num_candidates
        self.max_distance = max_distance
        self.rebuild_every = rebuild_every
        self.num_builds = 0
        self._calls_since_build = 0
        self._candidates: torch.Tensor | None = None

    def invalidate(self) -> None:
        self._candidates = None

    def state_dict(self) -> dict:
        """The cached candidates and schedule position (a resumed run continues exactly)."""
        return {"candidates": self._candidates, "calls_since_build": self._calls_since_build}

    def load_state_dict(self, state: dict) -> None:
        self._candidates = state["candidates"]
        self._calls_since_build = int(state["calls_since_build"])

    def candidates(self, means: torch.Tensor, from_touch: torch.Tensor) -> torch.Tensor:
        """[P, num_candidates] global indices of G_t Gaussians (``-1`` where fewer lie within reach)."""
        if self._candidates is None or self._calls_since_build >= self.rebuild_every:
            self._candidates = self._build(means, from_touch)
            self._calls_since_build = 0
        self._calls_since_build += 1
        return self._candidates

    def _build(self, means: torch.Tensor, from_touch: torch.Tensor) -> torch.Tensor:
        self.num_builds += 1
        touch_ids = torch.nonzero(from_touch, as_tuple=False)[:, 0].cpu().numpy()
        p = len(self.touch_points)
        if len(touch_ids) == 0:
            return torch.full((p, self.num_candidates), -1, dtype=torch.long)
        k = min(self.num_candidates, len(touch_ids))
        tree = cKDTree(means.detach()[from_touch].cpu().double().numpy())
        _, local = tree.query(self.touch_points, k=k, distance_upper_bound=self.max_distance)
        local = np.asarray(local).reshape(p, k)
        found = local < len(touch_ids)
        ids = np.full((p, self.num_candidates), -1, dtype=np.int64)
        ids[:, :k] = np.where(found, touch_ids[np.minimum(local, len(touch_ids) - 1)], -1)
        return torch.from_numpy(ids)


def transmittance_loss(
    touch_points: torch.Tensor,  # [P, 3]
    means: torch.Tensor,  # [N, 3]
    quats: torch.Tensor,  # [N, 4]
    scales: torch.Tensor,  # [N, 3] activated
    opacities: torch.Tensor,  # [N] activated
    candidates: torch.Tensor,  # [P, C] long, -1 = none
    top_k: int,
    max_distance: float,
) -> torch.Tensor:
    """Eq. 7 (minimised; the printed minus sign is a typo): L_T = 1/P sum_i T(p_i).

    T(p) (Eq. 6) is the mean of 1 - f(p; Sigma_j, mu_j) alpha_j over the ``top_k``
    candidates with the highest influence f alpha that lie within
    ``max_distance`` of p (live distance). A point with no Gaussian in reach has
    T(p) = 1: nothing blocks light there.
    """
    valid = candidates >= 0
    ids = candidates.clamp_min(0)
    used, inverse = torch.unique(ids, return_inverse=True)  # evaluate each Gaussian's precision once
    prec = precisions(quats[used], scales[used])[inverse]  # [P, C, 3, 3]
    mu = means[used][inverse]  # [P, C, 3]
    influence = gaussian_influence(touch_points, mu, prec) * opacities[used][inverse]  # [P, C]
    valid = valid & ((touch_points[:, None, :] - mu).norm(dim=-1) <= max_distance)
    ranked = torch.where(valid, influence, torch.full_like(influence, -1.0))
    k = min(top_k, ranked.shape[1])
    top, order = torch.topk(ranked, k, dim=1)
    top_valid = torch.gather(valid, 1, order)
    count = top_valid.sum(dim=1)
    transmittance = torch.where(top_valid, 1.0 - top, torch.zeros_like(top)).sum(dim=1)
    per_point = torch.where(count > 0, transmittance / count.clamp_min(1), torch.ones_like(transmittance))
    return per_point.mean()


# --------------------------------------------------------------------------- smoothness


def sobel_kernels_5x5(dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised 5x5 Sobel kernels (d/dx, d/dy) [1, 1, 5, 5]: a ramp of slope a per pixel gives a."""
    deriv, smooth = cv2.getDerivKernels(1, 0, 5, normalize=True)  # deriv [5, 1] sums |.| to 1, smooth sums to 1
    deriv = deriv[:, 0] / np.sum(deriv[:, 0] * (np.arange(5) - 2))  # unit response to a unit ramp
    kx = torch.as_tensor(np.outer(smooth[:, 0], deriv), dtype=dtype)
    return kx[None, None], kx.T.contiguous()[None, None]


def _gradients(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """|d/dx|, |d/dy| of [C, H, W] ('valid' convolution, [C, H-4, W-4]), both kernels in one call."""
    kx, ky = sobel_kernels_5x5(image.dtype)
    both = F.conv2d(image[:, None], torch.cat([kx, ky]).to(image.device)).abs()  # [C, 2, H-4, W-4]
    return both[:, 0], both[:, 1]


def image_edge_weights(image: torch.Tensor, beta: float = 10.0) -> torch.Tensor:  # image [H, W, 3]
    """The image factors of Eq. 8, e^{-beta |dI/dx|} and e^{-beta |dI/dy|}, [2, H-4, W-4].

    They depend on the ground-truth image only, so a trainer computes them once per view.
    """
    dx_i, dy_i = _gradients(image.permute(2, 0, 1))
    return torch.stack([torch.exp(-beta * dx_i.mean(0)), torch.exp(-beta * dy_i.mean(0))])


def expected_depth(depth: torch.Tensor, alpha: torch.Tensor, min_alpha: float = 1e-3) -> torch.Tensor:
    """Expected depth [H, W]: the accumulated depth of Eq. 5 [H, W] over the alpha [H, W] of the same pixels."""
    return depth / alpha.clamp_min(min_alpha)


def window_inside(mask: torch.Tensor) -> torch.Tensor:
    """[H-4, W-4] float: 1 where a pixel's whole 5x5 Sobel window lies in ``mask`` [H, W] bool, else 0."""
    window = F.max_pool2d((~mask).float()[None, None], kernel_size=5, stride=1)[0, 0]
    return 1.0 - window


def edge_aware_smoothness(
    depth: torch.Tensor,  # [H, W] rendered depth
    image: torch.Tensor | None = None,  # [H, W, 3] ground-truth image
    proximity: torch.Tensor | None = None,  # [H, W] in [0, 1]
    beta: float = 10.0,
    weights: torch.Tensor | None = None,  # [2, H-4, W-4] from image_edge_weights, instead of image
) -> torch.Tensor:
    """Eq. 8: mean of |dD/dx| e^{-beta |dI/dx|} + |dD/dy| e^{-beta |dI/dy|}, weighted by 1 - proximity.

    Gradients are 5x5 Sobel responses (paper Sec. 4.2.2), normalised so that a
    ramp of slope a per pixel gives a; the image gradient is the mean over
    colour channels. Only pixels whose 5x5 window lies inside the image count.
    """
    if weights is None:
        if image is None or depth.ndim != 2 or image.shape[:2] != depth.shape:
            raise InvalidInputError(
                f"edge_aware_smoothness: depth {tuple(depth.shape)} needs an image of the same size, got "
                f"{None if image is None else tuple(image.shape)}"
            )
        weights = image_edge_weights(image, beta)
    elif depth.ndim != 2 or tuple(weights.shape) != (2, depth.shape[0] - 4, depth.shape[1] - 4):
        raise InvalidInputError(
            f"edge_aware_smoothness: weights {tuple(weights.shape)} do not fit depth {tuple(depth.shape)}"
        )
    dx_d, dy_d = _gradients(depth[None])
    term = dx_d[0] * weights[0] + dy_d[0] * weights[1]
    if proximity is not None:
        term = term * (1.0 - proximity[2:-2, 2:-2])
    return term.mean()


def visible_touch_pixels(
    touch_points: np.ndarray,  # [P, 3] world
    K: np.ndarray,  # [3, 3]
    T_world_cam: np.ndarray,  # [4, 4]
    width: int,
    height: int,
    rendered_depth: np.ndarray | None = None,  # [H, W] expected depth, <= 0 where nothing was rendered
    occlusion_tolerance: float = 0.005,
) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the touch points seen in a view: projected inside it, in front, not occluded.

    A point is occluded when the rendered surface at its pixel lies more than
    ``occlusion_tolerance`` metres in front of it.
    """
    uv, z = project_points(touch_points, K, T_world_cam)
    inside = (z > 0) & np.isfinite(uv).all(axis=1)
    cols = np.floor(np.where(inside, uv[:, 0], -1)).astype(np.int64)
    rows = np.floor(np.where(inside, uv[:, 1], -1)).astype(np.int64)
    inside &= (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
    rows, cols, z = rows[inside], cols[inside], z[inside]
    if rendered_depth is not None:
        surface = rendered_depth[rows, cols]
        visible = (surface <= 0) | (z <= surface + occlusion_tolerance)
        rows, cols = rows[visible], cols[visible]
    return rows, cols


def proximity_mask(rows: np.ndarray, cols: np.ndarray, width: int, height: int, sigma_px: float) -> np.ndarray:
    """Sec. 4.2.2 proximity mask [H, W] float32: exp(-d^2 / (2 sigma^2)), d the distance to the nearest touch pixel.

    ``d`` is the exact Euclidean distance transform (cv2.distanceTransform) in
    pixels; the mask is 1 on a touch pixel and all zeros when no touch is seen.
    """
    if len(rows) == 0:
        return np.zeros((height, width), dtype=np.float32)
    if not sigma_px > 0:
        raise InvalidInputError(f"proximity_mask: sigma_px must be positive, got {sigma_px}")
    free = np.full((height, width), 255, dtype=np.uint8)
    free[rows, cols] = 0
    distance = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.exp(-(distance.astype(np.float64) ** 2) / (2.0 * sigma_px**2)).astype(np.float32)
