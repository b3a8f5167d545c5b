"""Pure-PyTorch reference of the rasterizer (autograd backward): the test oracle.

Two stages, as in gsplat:

* :func:`project_gaussians` -- gsplat's classic EWA projection (also used by the
  ``cpu`` backend, whose compositing is compiled but whose projection stays in
  torch so that ``means2d`` is a real autograd node for densification).
* :func:`rasterize_to_pixels_torch` -- front-to-back alpha compositing of
  depth-sorted Gaussians, pixel centres at +0.5, evaluated tile by tile (16x16)
  with dense [pixels, Gaussians] tensors per tile. Readable, not fast.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from tacsplat.reconstruction.gaussians import quats_to_rotmats

ALPHA_THRESHOLD = 1.0 / 255.0  # a Gaussian with alpha under this is skipped at a pixel
MAX_ALPHA = 0.999  # default alpha clamp: gsplat's (its CUDA kernels fix it), so every backend renders alike
TRANSMITTANCE_THRESHOLD = 1e-4  # a pixel stops once its transmittance would fall to this
GAUSSIAN_EXTEND = 3.33  # bounding box half-size, in standard deviations per axis
FOV_CLAMP = 1.3  # the EWA Jacobian is evaluated at x/z, y/z clamped to 1.3x the half field of view


@dataclass
class Projection:
    """Per-camera 2D Gaussians (C cameras, N Gaussians)."""

    means2d: Tensor  # [C, N, 2] pixel coordinates
    conics: Tensor  # [C, N, 3] upper triangle (a, b, c) of the inverse 2D covariance
    depths: Tensor  # [C, N] camera z (0 where culled)
    radii: Tensor  # [C, N, 2] int32 box half-sizes in pixels, 0 = culled
    opacities: Tensor  # [C, N] opacities (times the antialiasing compensation if used)


def project_gaussians(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    viewmats: Tensor,  # [C, 4, 4]
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    radius_clip: float = 0.0,
    antialiased: bool = False,
) -> Projection:
    """gsplat's classic EWA projection of 3D Gaussians into C pinhole cameras.

    A Gaussian is culled (radii 0) when its depth is outside [near, far], its
    dilated 2D covariance is not positive definite, its opacity is under 1/255,
    both radii are <= radius_clip, or its box misses the image.

    The covariances, their determinants and the antialiasing ratio are computed in float64 (per Gaussian, as in
    the ``cpu`` backend's projection) and the conics cast back: in float32 the determinant of a Gaussian large
    on screen overflows and it would be culled.
    """
    wide = torch.float64
    rotmats = quats_to_rotmats(quats)  # [N, 3, 3] (in the quaternions' precision, as on the cpu backend)
    m = rotmats.to(wide) * scales.to(wide)[:, None, :]  # R @ diag(s)
    covars = m @ m.transpose(-1, -2)  # [N, 3, 3] float64

    R = viewmats[:, :3, :3]  # [C, 3, 3]
    t = viewmats[:, :3, 3]  # [C, 3]
    means_c = torch.einsum("cij,nj->cni", R, means) + t[:, None, :]  # [C, N, 3]
    covars_c = torch.einsum("cij,njk,clk->cnil", R.to(wide), covars, R.to(wide))  # [C, N, 3, 3] float64

    x, y, z = means_c.unbind(-1)
    in_depth = (z >= near_plane) & (z <= far_plane)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]  # [C, 1]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    margin = FOV_CLAMP - 1.0
    lim_x_pos, lim_x_neg = (width - cx) / fx + margin * tan_fovx, cx / fx + margin * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + margin * tan_fovy, cy / fy + margin * tan_fovy
    rz = 1.0 / z_safe
    tx = z_safe * torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, x * rz))
    ty = z_safe * torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, y * rz))
    zeros = torch.zeros_like(z)
    J = torch.stack([fx * rz, zeros, -fx * tx * rz * rz, zeros, fy * rz, -fy * ty * rz * rz], dim=-1)  # [C, N, 6]
    J_wide = J.unflatten(-1, (2, 3)).to(wide)  # [C, N, 2, 3]
    cov2d = J_wide @ covars_c @ J_wide.transpose(-1, -2)  # [C, N, 2, 2] float64
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)  # [C, N, 2]

    a = cov2d[..., 0, 0] + eps2d
    b = cov2d[..., 0, 1]
    c = cov2d[..., 1, 1] + eps2d
    det = a * c - b * b
    opac = opacities.expand_as(z)
    if antialiased:
        det_orig = cov2d[..., 0, 0] * cov2d[..., 1, 1] - b * b
        # sqrt's gradient is infinite at 0 (a flat Gaussian seen edge-on): below 1e-8 the factor is 0, no gradient
        ratio = det_orig / det.clamp_min(1e-30)
        factor = torch.where(ratio > 1e-8, torch.sqrt(ratio.clamp_min(1e-8)), torch.zeros_like(ratio))
        opac = opac * factor.to(opac.dtype)
    positive = det > 0
    det_safe = torch.where(positive, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1).to(means.dtype)  # [C, N, 3]

    with torch.no_grad():
        visible = in_depth & positive & (opac >= ALPHA_THRESHOLD)
        extend = torch.sqrt(2.0 * torch.log(opac.clamp_min(ALPHA_THRESHOLD) / ALPHA_THRESHOLD))
        extend = extend.clamp_max(GAUSSIAN_EXTEND)
        radius_x = torch.ceil(extend * torch.sqrt(a.clamp_min(0.0)))
        radius_y = torch.ceil(extend * torch.sqrt(c.clamp_min(0.0)))
        visible &= ~((radius_x <= radius_clip) & (radius_y <= radius_clip))
        mx, my = means2d[..., 0], means2d[..., 1]
        visible &= (mx + radius_x > 0) & (mx - radius_x < width) & (my + radius_y > 0) & (my - radius_y < height)
        visible &= torch.isfinite(radius_x) & torch.isfinite(radius_y)
        radii = torch.stack([radius_x, radius_y], dim=-1).clamp_max(2**30) * visible[..., None]
        radii = radii.to(torch.int32)

    keep = visible[..., None]
    return Projection(
        means2d=torch.where(keep, means2d, torch.zeros_like(means2d)),
        conics=torch.where(keep, conics, torch.zeros_like(conics)),
        depths=torch.where(visible, z, zeros),
        radii=radii,
        opacities=opac,
    )


def tile_intersections(
    means2d: Tensor,  # [N, 2]
    radii: Tensor,  # [N, 2] int
    depths: Tensor,  # [N]
    width: int,
    height: int,
    tile_size: int,
) -> tuple[Tensor, Tensor]:
    """Depth-sorted (tile, Gaussian) pairs: returns ``(tile_ids [M], gauss_ids [M])`` sorted by tile then depth."""
    tiles_x = math.ceil(width / tile_size)
    tiles_y = math.ceil(height / tile_size)
    visible = (radii > 0).any(dim=-1).nonzero().squeeze(-1)
    if visible.numel() == 0:
        empty = torch.zeros(0, dtype=torch.long, device=means2d.device)
        return empty, empty
    m = means2d[visible].detach()
    r = radii[visible].to(m.dtype)
    x0 = torch.floor((m[:, 0] - r[:, 0]) / tile_size).clamp(0, tiles_x).long()
    x1 = torch.ceil((m[:, 0] + r[:, 0]) / tile_size).clamp(0, tiles_x).long()
    y0 = torch.floor((m[:, 1] - r[:, 1]) / tile_size).clamp(0, tiles_y).long()
    y1 = torch.ceil((m[:, 1] + r[:, 1]) / tile_size).clamp(0, tiles_y).long()
    nx, ny = (x1 - x0).clamp_min(0), (y1 - y0).clamp_min(0)
    counts = nx * ny
    owner = torch.repeat_interleave(torch.arange(visible.numel(), device=counts.device), counts)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(int(counts.sum()), device=counts.device) - first[owner]
    tile_x = x0[owner] + local % nx[owner]
    tile_y = y0[owner] + local // nx[owner]
    tile_ids = tile_y * tiles_x + tile_x
    # rank Gaussians by (depth, index), then sort intersections by (tile, rank)
    depth_rank = torch.sort(depths[visible].detach(), stable=True).indices.argsort()  # the inverse permutation
    order = torch.sort(tile_ids * visible.numel() + depth_rank[owner]).indices
    return tile_ids[order], visible[owner[order]]


def _composite_tile(
    px: Tensor,  # [P] pixel centre x
    py: Tensor,  # [P]
    means2d: Tensor,  # [M, 2] depth-sorted
    conics: Tensor,  # [M, 3]
    colors: Tensor,  # [M, D]
    opacities: Tensor,  # [M]
    depths: Tensor,  # [M] (no gradient)
    max_alpha: float = MAX_ALPHA,
) -> tuple[Tensor, Tensor, Tensor]:
    """Front-to-back compositing of M sorted Gaussians at P pixels -> (colour [P, D], transmittance [P],
    median depth [P]: the depth at which the transmittance first falls below 0.5, 0 if it never does)."""
    dx = means2d[None, :, 0] - px[:, None]  # [P, M]
    dy = means2d[None, :, 1] - py[:, None]
    sigma = 0.5 * (conics[None, :, 0] * dx * dx + conics[None, :, 2] * dy * dy) + conics[None, :, 1] * dx * dy
    alpha = torch.clamp(opacities[None, :] * torch.exp(-sigma), max=max_alpha)
    alpha = torch.where((sigma >= 0) & (alpha >= ALPHA_THRESHOLD), alpha, torch.zeros_like(alpha))
    # A pixel stops before the Gaussian that would bring its transmittance to <= 1e-4.
    with torch.no_grad():
        keep = torch.cumprod(1.0 - alpha, dim=1) > TRANSMITTANCE_THRESHOLD
    alpha = alpha * keep
    t_after = torch.cumprod(1.0 - alpha, dim=1)  # [P, M]
    t_before = torch.cat([torch.ones_like(t_after[:, :1]), t_after[:, :-1]], dim=1)
    weights = alpha * t_before
    with torch.no_grad():
        crossing = (t_before >= 0.5) & (t_after < 0.5)  # [P, M], at most one per row
        median = (crossing * depths[None, :]).sum(dim=1)
    return weights @ colors, t_after[:, -1], median


def rasterize_to_pixels_torch(
    means2d: Tensor,  # [C, N, 2]
    conics: Tensor,  # [C, N, 3]
    colors: Tensor,  # [C, N, D]
    opacities: Tensor,  # [C, N]
    radii: Tensor,  # [C, N, 2]
    depths: Tensor,  # [C, N] sort keys
    width: int,
    height: int,
    tile_size: int = 16,
    backgrounds: Tensor | None = None,  # [C, D]
    max_alpha: float = MAX_ALPHA,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite projected Gaussians into images -> (colors [C, H, W, D], alphas [C, H, W, 1], median [C, H, W, 1]).

    ``median`` is the median depth, forward only (no gradient): the ``depths`` value of the Gaussian
    at which the transmittance first falls below 0.5, 0 where it never does.
    """
    n_cams, _, n_ch = colors.shape
    tiles_x = math.ceil(width / tile_size)
    device = means2d.device
    out_colors, out_alphas, out_median = [], [], []
    for cam in range(n_cams):
        tile_ids, gauss_ids = tile_intersections(means2d[cam], radii[cam], depths[cam], width, height, tile_size)
        bounds = torch.searchsorted(tile_ids, torch.arange(tiles_x * math.ceil(height / tile_size) + 1, device=device))
        drawn = []  # (pixel indices, colour, transmittance, median depth) of each tile
        for tile in torch.unique_consecutive(tile_ids).tolist():
            ids = gauss_ids[bounds[tile] : bounds[tile + 1]]
            ty, tx = divmod(tile, tiles_x)
            ys = torch.arange(ty * tile_size, min((ty + 1) * tile_size, height), device=device)
            xs = torch.arange(tx * tile_size, min((tx + 1) * tile_size, width), device=device)
            gy, gx = torch.meshgrid(ys, xs, indexing="ij")
            gy, gx = gy.reshape(-1), gx.reshape(-1)
            per_gauss = (t[cam, ids] for t in (means2d, conics, colors, opacities, depths.detach()))
            color, trans, median = _composite_tile(
                gx.to(means2d.dtype) + 0.5, gy.to(means2d.dtype) + 0.5, *per_gauss, max_alpha
            )
            drawn.append((gy * width + gx, color, trans, median))
        if not drawn:  # nothing drawn: copy zero pixels, so that every input still gets a (zero) gradient
            trans = means2d[cam, :0, 0] + conics[cam, :0, 0] + opacities[cam, :0]
            drawn.append((torch.zeros(0, dtype=torch.long, device=device), colors[cam, :0], trans, depths[cam, :0]))
        index, color, trans, median = (torch.cat(parts) for parts in zip(*drawn))
        blank = torch.zeros(height * width, dtype=colors.dtype, device=device)
        trans_img = torch.ones_like(blank).index_copy(0, index, trans)
        color_img = torch.zeros(height * width, n_ch, dtype=colors.dtype, device=device).index_copy(0, index, color)
        if backgrounds is not None:
            color_img = color_img + trans_img[:, None] * backgrounds[cam][None, :]
        out_colors.append(color_img.reshape(height, width, n_ch))
        out_alphas.append((1.0 - trans_img).reshape(height, width, 1))
        out_median.append(blank.index_copy(0, index, median.detach().to(blank.dtype)).reshape(height, width, 1))
    return torch.stack(out_colors), torch.stack(out_alphas), torch.stack(out_median)
