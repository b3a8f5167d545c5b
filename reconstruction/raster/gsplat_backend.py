"""Adapter to ``gsplat.rasterization`` (CUDA), used only when CUDA and gsplat are present."""

from __future__ import annotations

from torch import Tensor


def rasterization_gsplat(*args, **options) -> tuple[Tensor, Tensor, dict]:
    """Call ``gsplat.rasterization`` with the same arguments (means, quats, scales, opacities, colors, viewmats,
    Ks, width, height and its options); ``meta`` gains ``backend='gsplat'``."""
    import gsplat  # imported here: optional, CUDA only

    render_colors, render_alphas, meta = gsplat.rasterization(*args, **options)
    meta["backend"] = "gsplat"
    return render_colors, render_alphas, meta
