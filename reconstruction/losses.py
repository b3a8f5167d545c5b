"""The training losses of tactile-informed 3DGS (paper Sec. 3-4): photometric, 3D transmittance, smoothness.

Equation numbers refer to ``paper/tactile-informed-3dgs.tex``: Eq. 1 is the
Gaussian influence f(x; Sigma, mu), Eq. 6 the average transmittance T(p),
Eq. 7 the transmittance loss L_T and Eq. 8 the edge-aware smoothness L_S.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

from tacsplat.reconstruction.fused_normals import depth_normal_consistency_cpu
from tacsplat.reconstruction.fused_smoothness import albedo_smoothness_cpu, edge_aware_smoothness_cpu
from tacsplat.reconstruction.fused_ssim import d_ssim
from tacsplat.reconstruction.fused_touch import transmittance_cpu
from tacsplat.reconstruction.gaussians import whitening


def photometric_loss(
    rendered: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2, fused: bool = True
) -> torch.Tensor:
    """(1 - w) L1 + w D-SSIM of [H, W, 3] (or [B, H, W, 3]) images, w = 0.2 (Kerbl et al., paper Sec. 3); D-SSIM
    by the fused CPU kernels of :mod:`.fused_ssim` for CPU tensors unless ``fused`` is False (the torch reference)."""
    l1 = (rendered - target).abs().mean()
    return (1.0 - ssim_weight) * l1 + ssim_weight * d_ssim(rendered, target, fused)


def backdrop_alpha_loss(alpha: torch.Tensor, backdrop_mask: torch.Tensor) -> torch.Tensor:
    """Mean rendered alpha [H, W] over the pixels [H, W] bool that show the bare backdrop.

    Not in the paper: with few views, opaque Gaussians coloured like a smooth
    backdrop explain the images as well as empty space does, and they become
    floaters in every other view; this keeps the backdrop transparent.
    """
    return (alpha * backdrop_mask).sum() / backdrop_mask.sum().clamp_min(1)


# --------------------------------------------------------------------------- transmittance


MAX_MAHALANOBIS = 160.0  # exp(-80) ~ 2e-35 is still a normal float32; past it exp returns subnormal numbers,
# 8-20x slower on this CPU (torch.exp of 16k floats: 23 us, 180-450 us when results are subnormal), for an
# influence no loss can tell from 0
MIN_SCALE = 1e-12  # the touch loss floors scales here: S^-1's gradient 1/s^2 overflows float32 under ~1e-19 (0 * inf
# = NaN where the exponent is clamped) and an underflowed scale of 0 gives 0/0; thinner is a plane to the loss


def gaussian_influence(
    offsets: torch.Tensor,  # [P, K, 3] p - mu of each point and its K Gaussians
    whitened: torch.Tensor,  # [P, K, 3, 3] S^-1 R^T of each Gaussian (gaussians.whitening)
) -> torch.Tensor:
    """Eq. 1: f(p; Sigma, mu) = exp(-1/2 (p - mu)^T Sigma^-1 (p - mu)) for each point and its K Gaussians, [P, K]."""
    local = torch.einsum("pkij,pkj->pki", whitened, offsets)  # [P, K, 3]: the offset in the Gaussian's unit frame
    return torch.exp(-0.5 * (local * local).sum(-1).clamp(0.0, MAX_MAHALANOBIS))


class TouchNeighbours:
    """Candidate G_t Gaussians near each touch point, from a k-d tree on detached means.

    The tree is rebuilt every ``rebuild_every`` calls (and after
    :meth:`invalidate`, which densification must call because it renumbers the
    Gaussians), so the neighbour search costs little per iteration; the
    influence itself is always evaluated with the live parameters.
    """

    def __init__(self, touch_points: np.ndarray, num_candidates: int, max_distance: float, rebuild_every: int):
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
            self._candidates = self._build(means, from_touch).to(means.device)  # one transfer per rebuild
            self._calls_since_build = 0
        elif self._candidates.device != means.device:  # (restored from a checkpoint)
            self._candidates = self._candidates.to(means.device)
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
    fused: bool = True,
) -> torch.Tensor:
    """Eq. 7 (minimised; the printed minus sign is a typo): L_T = 1/P sum_i T(p_i); for CPU tensors the fused
    kernels of :mod:`.fused_touch` (same value and gradients, a tenth of the time) unless ``fused`` is False,
    elsewhere the torch below (their reference).

    T(p) (Eq. 6) is the mean of 1 - f(p; Sigma_j, mu_j) alpha_j over the ``top_k``
    candidates with the highest influence f alpha that lie within
    ``max_distance`` of p (live distance). A point with no Gaussian in reach has
    T(p) = 1: nothing blocks light there. Scales are floored at ``MIN_SCALE`` (no gradient below it). The fused
    kernels raise :class:`~tacsplat.errors.InvalidInputError` on NaN or infinite inputs; the reference returns NaN.
    """
    if fused and means.device.type == "cpu":
        return transmittance_cpu(
            touch_points, means, quats, scales, opacities, candidates, top_k, max_distance, MAX_MAHALANOBIS, MIN_SCALE
        )
    valid = candidates >= 0
    ids = candidates.clamp_min(0)
    if ids.is_cuda:  # finding the distinct ids would wait for the device; [P, C] whitenings cost it little
        used, inverse = ids.reshape(-1), torch.arange(ids.numel(), device=ids.device).reshape(ids.shape)
    else:  # each Gaussian's whitening once: distinct ids by marking (a sort, as in torch.unique, costs more)
        marked = torch.zeros(means.shape[0], dtype=torch.bool, device=ids.device)
        marked[ids] = True
        used = marked.nonzero()[:, 0]
        slot = torch.empty(means.shape[0], dtype=torch.long, device=ids.device)
        slot[used] = torch.arange(len(used), device=ids.device)
        inverse = slot[ids]
    white = whitening(quats[used], scales[used].clamp_min(MIN_SCALE))[inverse]  # [P, C, 3, 3]
    offset = touch_points[:, None, :] - means[used][inverse]  # [P, C, 3]
    influence = gaussian_influence(offset, white) * opacities[used][inverse]  # [P, C]
    valid = valid & ((offset * offset).sum(-1) <= max_distance**2)
    ranked = torch.where(valid, influence, torch.full_like(influence, -1.0))
    k = min(top_k, ranked.shape[1])
    top, order = torch.topk(ranked, k, dim=1)
    top_valid = torch.gather(valid, 1, order)
    count = top_valid.sum(dim=1)
    transmittance = torch.where(top_valid, 1.0 - top, torch.zeros_like(top)).sum(dim=1)
    per_point = torch.where(count > 0, transmittance / count.clamp_min(1), torch.ones_like(transmittance))
    return per_point.mean()


# --------------------------------------------------------------------------- smoothness


@functools.lru_cache(maxsize=None)
def sobel_kernels_5x5(dtype=torch.float32, device=None) -> torch.Tensor:
    """Normalised 5x5 Sobel kernels [2, 1, 5, 5] (d/dx, d/dy): a ramp of slope a per pixel gives a.

    Made once per dtype and device (a training step reuses them)."""
    deriv, smooth = cv2.getDerivKernels(1, 0, 5, normalize=True)  # deriv [5, 1] sums |.| to 1, smooth sums to 1
    deriv = deriv[:, 0] / np.sum(deriv[:, 0] * (np.arange(5) - 2))  # unit response to a unit ramp
    kx = torch.as_tensor(np.outer(smooth[:, 0], deriv), dtype=dtype, device=device)
    return torch.stack([kx, kx.T])[:, None].contiguous()


def _gradients(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """|d/dx|, |d/dy| of [C, H, W] ('valid' convolution, [C, H-4, W-4]), both kernels in one call."""
    both = F.conv2d(image[:, None], sobel_kernels_5x5(image.dtype, image.device)).abs()  # [C, 2, H-4, W-4]
    return both[:, 0], both[:, 1]


def image_edge_weights(image: torch.Tensor, beta: float = 10.0) -> torch.Tensor:  # image [H, W, 3]
    """The image factors of Eq. 8, e^{-beta |dI/dx|} and e^{-beta |dI/dy|}, [2, H-4, W-4].

    They depend on the ground-truth image only, so a trainer computes them once per view.
    """
    dx_i, dy_i = _gradients(image.permute(2, 0, 1))
    return torch.stack([torch.exp(-beta * dx_i.mean(0)), torch.exp(-beta * dy_i.mean(0))])


def image_pair_weights(image: torch.Tensor, beta: float) -> tuple[torch.Tensor, torch.Tensor]:  # image [H, W, 3]
    """e^{-beta |I(p) - I(q)|} of horizontally ([H, W-1]) and vertically ([H-1, W]) neighbouring pixels p, q of a
    ground-truth image (the difference averaged over colour channels): near 1 across gradual shading, near 0
    across a texture's edges. They depend on the image only, so a trainer computes them once per view."""
    across = (image[:, 1:] - image[:, :-1]).abs().mean(-1)
    down = (image[1:] - image[:-1]).abs().mean(-1)
    return torch.exp(-beta * across), torch.exp(-beta * down)


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
    fused: bool = True,
) -> torch.Tensor:
    """Eq. 8: mean of |dD/dx| e^{-beta |dI/dx|} + |dD/dy| e^{-beta |dI/dy|}, weighted by 1 - proximity.

    Gradients are 5x5 Sobel responses (paper Sec. 4.2.2), normalised so that a
    ramp of slope a per pixel gives a; the image gradient is the mean over
    colour channels. Only pixels whose 5x5 window lies inside the image count.
    For a CPU depth map the fused kernels of :mod:`.fused_smoothness` unless ``fused`` is False (the torch
    convolutions below, the reference).
    """
    weights = image_edge_weights(image, beta) if weights is None else weights  # (of the depth's size)
    if fused and depth.device.type == "cpu" and not weights.requires_grad:
        factors = weights if proximity is None else weights * (1.0 - proximity[2:-2, 2:-2].detach())
        return edge_aware_smoothness_cpu(depth, sobel_kernels_5x5(depth.dtype)[:, 0], factors)
    dx_d, dy_d = _gradients(depth[None])
    term = dx_d[0] * weights[0] + dy_d[0] * weights[1]
    if proximity is not None:
        term = term * (1.0 - proximity[2:-2, 2:-2])
    return term.mean()


def visible_touch_pixels(
    touch_points: torch.Tensor,  # [P, 3] world
    K: torch.Tensor,  # [3, 3]
    viewmat: torch.Tensor,  # [4, 4] world-to-camera
    width: int,
    height: int,
    rendered_depth: torch.Tensor | None = None,  # [H, W] expected depth, <= 0 where nothing was rendered
    occlusion_tolerance: float = 0.005,
) -> torch.Tensor:
    """[H, W] bool: the pixels of the touch points seen in a view (projected inside it, in front, not occluded).

    A point is occluded when the rendered surface at its pixel lies more than
    ``occlusion_tolerance`` metres in front of it. Computed on the tensors' device
    without host synchronisation (no data-dependent shapes).
    """
    p_cam = touch_points @ viewmat[:3, :3].T + viewmat[:3, 3]  # [P, 3]
    z = p_cam[:, 2]
    uv = p_cam[:, :2] / z.clamp_min(1e-12)[:, None] @ K[:2, :2].T + K[:2, 2]
    cols, rows = torch.floor(uv[:, 0]), torch.floor(uv[:, 1])
    seen = (z > 0) & torch.isfinite(uv).all(dim=1) & (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
    flat = torch.where(seen, rows * width + cols, torch.zeros_like(cols)).long()  # [P] row-major; 0 where unseen
    if rendered_depth is not None:
        surface = rendered_depth.reshape(-1)[flat]
        seen = seen & ((surface <= 0) | (z <= surface + occlusion_tolerance))
    pixels = torch.zeros(height * width, dtype=torch.float32, device=touch_points.device)
    pixels.scatter_reduce_(0, flat, seen.float(), reduce="amax")
    return pixels.reshape(height, width) > 0


def proximity_mask(seeds: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Sec. 4.2.2 proximity mask [H, W]: exp(-d^2 / (2 sigma^2)), d the distance to the nearest seed pixel.

    ``seeds`` [H, W] bool are the visible touch pixels. ``d`` is the exact Euclidean
    distance up to 4 sigma (two separable min-plus passes; beyond it the mask is
    below 3.4e-4 and set to 0); the mask is 1 on a seed and all zeros without seeds.
    The passes run on the seeds' bounding box widened by that reach (outside it the mask is 0; the same values),
    one shift at a time: memory of the box's size, whatever sigma.
    """
    reach = int(math.ceil(4.0 * sigma_px))
    mask = torch.zeros(seeds.shape, device=seeds.device, dtype=torch.float32)  # [H, W]
    rows, cols = seeds.any(dim=1).nonzero()[:, 0], seeds.any(dim=0).nonzero()[:, 0]
    if not len(rows):
        return mask
    y0, y1 = max(int(rows[0]) - reach, 0), min(int(rows[-1]) + reach + 1, seeds.shape[0])
    x0, x1 = max(int(cols[0]) - reach, 0), min(int(cols[-1]) + reach + 1, seeds.shape[1])
    far = float(2 * (reach + 1) ** 2)  # farther than any distance within reach
    d2 = torch.where(seeds[y0:y1, x0:x1], 0.0, far).to(torch.float32)  # [h, w]
    for dim in (0, 1):  # min over rows, then over columns, of the cost k^2 of a shift by k
        cost, n = d2, d2.shape[dim]
        d2 = cost.clone()
        for k in range(1, min(reach, n - 1) + 1):
            for to, of in ((0, k), (k, 0)):  # from the pixel k after, and from the one k before
                near = d2.narrow(dim, to, n - k)
                torch.minimum(near, cost.narrow(dim, of, n - k) + float(k * k), out=near)
    mask[y0:y1, x0:x1] = torch.where(d2 < far, torch.exp(-d2 / (2.0 * sigma_px**2)), torch.zeros_like(d2))
    return mask


# --------------------------------------------------------------------------- geometry (beyond the paper)


def depth_normals(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Camera-frame unit normals [H, W, 3] of a z-depth map [H, W] (central differences of the unprojected
    points, turned towards the camera; 0 on the one-pixel border and where depth is not positive around).

    Each coordinate is its own [H, W] map (no [H, W, 3] stacks until the end): half the time of the stacked form."""
    rx = (torch.arange(depth.shape[1], device=depth.device, dtype=depth.dtype) + 0.5 - K[0, 2]) / K[0, 0]  # [W]
    ry = (torch.arange(depth.shape[0], device=depth.device, dtype=depth.dtype) + 0.5 - K[1, 2]) / K[1, 1]  # [H]
    x, y, z = rx * depth, ry[:, None] * depth, depth  # [H, W]: the unprojected points
    ux, uy, uz = (c[1:-1, 2:] - c[1:-1, :-2] for c in (x, y, z))  # [H-2, W-2]: along the row
    vx, vy, vz = (c[2:, 1:-1] - c[:-2, 1:-1] for c in (x, y, z))  # down the column
    nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx  # du x dv
    inverse_length = (nx * nx + ny * ny + nz * nz).clamp_min(1e-24).rsqrt()  # a zero normal stays 0, gradient 0
    away = nx * x[1:-1, 1:-1] + ny * y[1:-1, 1:-1] + nz * z[1:-1, 1:-1] > 0  # facing away: turn it round
    valid = (depth > 0).float()
    around = F.max_pool2d(1.0 - valid[None, None], 3, stride=1)[0, 0] == 0  # [H-2, W-2]: all 9 positive
    scale = torch.where(away, -inverse_length, inverse_length) * around
    return F.pad(torch.stack([nx * scale, ny * scale, nz * scale]), (1, 1, 1, 1)).permute(1, 2, 0)


def normal_consistency_loss(rendered: torch.Tensor, from_depth: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Depth-normal consistency (2DGS): the alpha-weighted mean of 1 - <rendered normal, depth normal> over the
    pixels where the depth normal is known ([H, W, 3] unit normals, alpha [H, W])."""
    known = ((from_depth * from_depth).sum(-1) > 0.25).float() * alpha  # unit normals where known, 0 elsewhere
    return ((1.0 - (rendered * from_depth).sum(-1)) * known).sum() / known.sum().clamp_min(1e-6)


def depth_normal_consistency(
    rendered: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, weight: torch.Tensor, fused: bool = True
) -> torch.Tensor:
    """:func:`normal_consistency_loss` of the rendered normals [H, W, 3] against :func:`depth_normals` of the
    z-depth [H, W] (weights [H, W], no gradient); for CPU tensors in one fused pass each way
    (:mod:`.fused_normals`) unless ``fused`` is False."""
    if fused and depth.device.type == "cpu":
        return depth_normal_consistency_cpu(rendered, depth, K, weight)
    return normal_consistency_loss(rendered, depth_normals(depth, K), weight)


def flatten_loss(scales: torch.Tensor, scene_scale: float) -> torch.Tensor:
    """Minimum-scale loss (PGSR): the mean shortest axis [N, 3] of the Gaussians, in units of the scene scale;
    it makes Gaussians surfel-like so that their shortest axis is a normal."""
    return scales.min(dim=-1).values.mean() / scene_scale


def albedo_smoothness_loss(
    albedo: torch.Tensor,
    inside: torch.Tensor,
    pair_weights: tuple[torch.Tensor, torch.Tensor] | None = None,
    fused: bool = True,
) -> torch.Tensor:
    """L1 differences [] of the rendered diffuse colour ``albedo`` [H, W, 3] between horizontally and vertically
    neighbouring pixels that are both ``inside`` [H, W] bool the silhouette, each times its ``pair_weights``
    ([H, W-1], [H-1, W], no gradient; None: 1, see :func:`image_pair_weights`), summed over the pairs inside and
    divided by their number (0 with no such pair). It flattens the gradual shading a free diffuse colour would
    otherwise paint: that shading then has to come from the normals (through the sh-lit appearance's light). L1, and weights that vanish across the image's edges, leave a texture's edges to
    the albedo (Retinex's assumption: shading varies slowly, reflectance in steps). For CPU tensors the fused
    kernels of :mod:`.fused_smoothness` unless ``fused`` is False (the torch below, the reference)."""
    if pair_weights is None:
        pair_weights = (
            albedo.new_ones(albedo.shape[0], albedo.shape[1] - 1),
            albedo.new_ones(albedo.shape[0] - 1, albedo.shape[1]),
        )
    if fused and albedo.device.type == "cpu":
        return albedo_smoothness_cpu(albedo, inside, *pair_weights)
    inside = inside.to(albedo.dtype)
    across = inside[:, 1:] * inside[:, :-1]  # [H, W-1]
    down = inside[1:] * inside[:-1]  # [H-1, W]
    total = ((albedo[:, 1:] - albedo[:, :-1]).abs().sum(-1) * across * pair_weights[0]).sum() + (
        (albedo[1:] - albedo[:-1]).abs().sum(-1) * down * pair_weights[1]
    ).sum()
    return total / (across.sum() + down.sum()).clamp_min(1.0)
