"""`tacsplat bench rasterizer`: the ``cpu`` backend against the ``torch`` reference.

Also home of :func:`random_scene`, the random Gaussian scenes used by the
benchmark and by the rasterizer tests.
"""

from __future__ import annotations

import math


def random_scene(
    n: int,
    width: int,
    height: int,
    n_cams: int = 1,
    sh_degree: int | None = 3,
    radius_px: tuple[float, float] = (1.0, 8.0),
    seed: int = 0,
    dtype=None,
) -> dict:
    """N random Gaussians filling the frustum of C cameras; 3-sigma radii roughly uniform in ``radius_px``.

    Returns the keyword arguments of ``rasterization`` (means, quats, scales,
    opacities, colors, viewmats, Ks, width, height, sh_degree). Camera 0 is at
    the origin looking down +z; the others are turned about the y axis around
    the cloud's centre (3 m ahead).
    """
    import torch

    dtype = dtype or torch.float32
    f64 = torch.float64
    g = torch.Generator().manual_seed(seed)
    focal = 0.9 * max(width, height)
    depth = 2.5 + torch.rand(n, generator=g, dtype=f64)  # [N]
    px = torch.rand(n, generator=g, dtype=f64) * width
    py = torch.rand(n, generator=g, dtype=f64) * height
    means = torch.stack([(px - width / 2) / focal * depth, (py - height / 2) / focal * depth, depth], dim=-1)
    radius = radius_px[0] + torch.rand(n, generator=g, dtype=f64) * (radius_px[1] - radius_px[0])
    sigma_px = radius / 3.0
    base = sigma_px * depth / focal  # world-space standard deviation giving that pixel size
    scales = base[:, None] * torch.exp((torch.rand(n, 3, generator=g, dtype=f64) - 0.5) * 0.8)
    quats = torch.randn(n, 4, generator=g, dtype=f64)
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g, dtype=f64)
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=g, dtype=f64)
    else:
        colors = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=f64) * 0.3
    viewmats = torch.eye(4, dtype=f64).repeat(n_cams, 1, 1)
    centre = torch.tensor([0.0, 0.0, 3.0], dtype=f64)
    for c in range(1, n_cams):
        ang = 0.12 * c
        rot = torch.tensor(
            [[math.cos(ang), 0.0, math.sin(ang)], [0.0, 1.0, 0.0], [-math.sin(ang), 0.0, math.cos(ang)]], dtype=f64
        )
        viewmats[c, :3, :3] = rot
        viewmats[c, :3, 3] = centre - rot @ centre
    Ks = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=f64).repeat(n_cams, 1, 1)
    scene = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmats=viewmats, Ks=Ks)
    scene = {k: v.to(dtype).contiguous() for k, v in scene.items()}
    scene.update(width=width, height=height, sh_degree=sh_degree)
    return scene


def register(cli) -> None:
    """Add `bench rasterizer` (filled in below)."""
