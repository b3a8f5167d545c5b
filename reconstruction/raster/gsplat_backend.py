"""Adapter to ``gsplat.rasterization`` (CUDA), used only when CUDA and gsplat are present."""

from __future__ import annotations

from torch import Tensor


def rasterization_gsplat(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, D], [C, N, D] or [N, K, 3]
    viewmats: Tensor,  # [C, 4, 4]
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    **options,
) -> tuple[Tensor, Tensor, dict]:
    """Call gsplat with the same arguments; ``meta`` gains ``backend='gsplat'``."""
    import gsplat  # imported here: optional, CUDA only

    render_colors, render_alphas, meta = gsplat.rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, **options
    )
    meta["backend"] = "gsplat"
    return render_colors, render_alphas, meta
