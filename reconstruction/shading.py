"""What a view of the Gaussians looks like: colour, alpha, depth and normals from one rasterization pass.

:func:`render` is the one place the trainer and the evaluation turn Gaussians into images.
Its extra outputs ride in the same pass as extra colour channels:

* **normals** -- each Gaussian's normal is its shortest axis (:func:`gaussian_normals`),
  turned towards the camera and expressed in the camera frame; the pass blends them like
  colours, and the pixel normal is that sum normalised (2DGS / PGSR style);
* **appearance** -- ``"sh"``: the view-dependent colour of the SH coefficients (3DGS);
  ``"sh-lit"``: a deferred shading of that colour as an albedo, times the irradiance of a learned distant
  light at the pixel's normal (:class:`DiffuseLight`), saturating at 1 as a camera's does. Shading then has
  to come from the normals, which ties the colours of the views to the geometry even where a glossy surface
  has no texture; the SH bands above the first keep the view-dependent part (highlights, reflections).

Plain RGB(+depth) with SH goes straight through :func:`rasterization` (its fused SH path).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from tacsplat.reconstruction.config import Appearance
from tacsplat.reconstruction.fused_normals import gaussian_normals_cpu
from tacsplat.reconstruction.fused_shading import ALPHA_FLOOR, shade_cpu
from tacsplat.reconstruction.gaussians import Gaussians, quats_to_rotmats
from tacsplat.reconstruction.raster import rendering as raster  # the module: tests spy on its calls
from tacsplat.reconstruction.raster.spherical_harmonics import SH_C0, sh_basis


def fused_kernels(backend: str) -> bool:
    """Whether the fused CPU kernels (the Gaussians' normals, the deferred shading, the losses) run for CPU
    tensors: on every backend but ``"torch"``, which stays the pure-PyTorch reference end to end."""
    return backend != "torch"


def gaussian_normals(quats: Tensor, scales: Tensor, fused: bool = True) -> Tensor:
    """Unit normals [N, 3]: the rotation's column of each Gaussian's shortest axis (sign arbitrary). For CPU
    tensors the numba kernels of :mod:`.fused_normals` unless ``fused`` is False (this torch reference)."""
    if fused and quats.device.type == "cpu":
        return gaussian_normals_cpu(quats, scales)
    rotations = quats_to_rotmats(quats)  # [N, 3, 3]
    shortest = scales.detach().argmin(dim=-1)  # [N]
    return torch.gather(rotations, 2, shortest[:, None, None].expand(-1, 3, 1))[..., 0]


class DiffuseLight(torch.nn.Module):
    """A learned distant light as a diffuse surface receives it: the irradiance [..., 3] at a world normal ``n``
    seen along the world view direction ``v`` is ``max(SH_2(n) . c + k * max(<n, -v>, 0), 0)``.

    ``c`` [9, 3]: second-order spherical harmonics, which hold a distant light's irradiance (a clamped-cosine
    convolution) to within a few per cent (Ramamoorthi & Hanrahan 2001); ``k`` [3]: a light at the camera (a lamp
    beside the lens, or a renderer's headlight). It starts as uniform irradiance 1 with no camera light, so
    that a lit colour starts as its albedo.
    """

    def __init__(self, device=None):
        super().__init__()
        coefficients = torch.zeros((9, 3), device=device)
        coefficients[0] = 1.0 / SH_C0
        self.coefficients = torch.nn.Parameter(coefficients)
        self.camera = torch.nn.Parameter(torch.zeros(3, device=device))

    def irradiance(self, normals: Tensor, views: Tensor) -> Tensor:
        """Irradiance [..., 3] at unit world ``normals`` [..., 3] seen along unit world ``views`` [..., 3]."""
        facing = (-(normals * views).sum(-1, keepdim=True)).clamp_min(0.0)  # [..., 1]
        return (sh_basis(2, normals) @ self.coefficients + facing * self.camera).clamp_min(0.0)


@dataclass
class Look:
    """How Gaussians are coloured: their ``appearance`` and, for "sh-lit", the diffuse light (None: the albedo
    unlit)."""

    appearance: Appearance = "sh"
    light: DiffuseLight | None = None


@dataclass
class RenderOutput:
    rgb: Tensor  # [H, W, 3] colour before the background (alpha-premultiplied)
    alpha: Tensor  # [H, W]
    depth: Tensor | None  # [H, W] accumulated ("D") or expected ("ED") depth
    normal: Tensor | None  # [H, W, 3] unit camera-frame normal towards the camera (0 where nothing is drawn)
    meta: dict
    albedo: Tensor | None = None  # [H, W, 3] the blended diffuse colour per unit alpha ("sh-lit")


def render(
    gaussians: Gaussians,
    viewmat: Tensor,  # [1, 4, 4] world-to-camera
    K: Tensor,  # [1, 3, 3]
    width: int,
    height: int,
    *,
    sh_degree: int,
    backend: str,
    depth_mode: Literal["D", "ED"] | None = None,
    normals: bool = False,
    appearance: Appearance = "sh",
    light: DiffuseLight | None = None,  # "sh-lit": the diffuse light (None: unlit, the albedo)
) -> RenderOutput:
    """Render one view; see the module docstring for what each option adds to the pass."""
    g = gaussians
    plain = not normals and appearance == "sh"  # SH colour straight through rasterization's fused SH path
    colors, degree = g.sh_coefficients(sh_degree), sh_degree
    if not plain:
        campos = -viewmat[0, :3, :3].T @ viewmat[0, :3, 3]  # [3]
        features = raster.sh_colors(sh_degree, g.means, campos, colors, backend)  # [N, 3]
        n = gaussian_normals(g.quats, g.scales, fused_kernels(backend))
        n = torch.where(((n * (g.means - campos)).sum(-1, keepdim=True) > 0), -n, n)  # towards the camera
        colors, degree = torch.cat([features, n @ viewmat[0, :3, :3].T], dim=-1)[None], None  # camera-frame normals
    mode = "RGB" if depth_mode is None else f"RGB+{depth_mode}"
    splats = (g.means, g.quats, g.scales, g.opacities, colors)
    out, alphas, meta = raster.rasterization(
        *splats, viewmat, K, width, height, sh_degree=degree, render_mode=mode, backend=backend
    )
    alpha = alphas[0, ..., 0]
    if plain:
        out = out[0]
        return RenderOutput(out[..., :3], alpha, None if depth_mode is None else out[..., -1], None, meta)
    blended, normal, depth = _Channels.apply(out)
    if appearance == "sh":
        return RenderOutput(blended, alpha, depth, normal, meta)
    rgb, albedo = _shade(blended, alpha, normal, viewmat[0], K[0], light, fused=fused_kernels(backend))
    return RenderOutput(rgb, alpha, depth, normal, meta, albedo)


_NORMAL_EPS = 1e-8  # F.normalize's eps for the rendered normal


class _Channels(torch.autograd.Function):
    """One camera's rendered channels [1, H, W, 6 or 7] (colour, normal sum, and the depth if rendered) -> colour
    [H, W, 3], unit normal [H, W, 3] (``F.normalize``'s, eps 1e-8) and depth [H, W] (None with 6 channels). The
    same as slicing and ``F.normalize``, with one gradient tensor in the backward: each slice's backward would fill
    a zero tensor of the whole's size, and the normalisation take five image-sized ops."""

    @staticmethod
    def forward(ctx, out: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        summed = out[0, ..., 3:6]
        norm = torch.linalg.vector_norm(summed, dim=-1, keepdim=True).clamp_min(_NORMAL_EPS)  # [H, W, 1]
        normal = summed / norm
        ctx.save_for_backward(normal, norm)
        ctx.channels = out.shape[-1]
        depth = out[0, ..., 6].contiguous() if out.shape[-1] == 7 else None
        return out[0, ..., :3].contiguous(), normal, depth

    @staticmethod
    def backward(ctx, v_color: Tensor, v_normal: Tensor, v_depth: Tensor | None) -> Tensor:
        normal, norm = ctx.saved_tensors
        v_out = v_normal.new_empty(1, *normal.shape[:2], ctx.channels)  # [1, H, W, C], all written
        v_out[0, ..., :3] = v_color
        # d(x / |x|) = (v - n (v . n)) / |x|; where |x| is clamped at eps, n = x / eps and the gradient is v / eps
        along = torch.where(norm > _NORMAL_EPS, (v_normal * normal).sum(-1, keepdim=True), 0.0)
        v_out[0, ..., 3:6] = (v_normal - normal * along) / norm
        if ctx.channels == 7:  # (an unused depth's gradient arrives as zeros: autograd materialises it)
            v_out[0, ..., 6] = v_depth
        return v_out


def pixel_rays(K: Tensor, width: int, height: int) -> Tensor:
    """Unit camera-frame ray directions [H, W, 3] through the pixel centres (+0.5)."""
    v, u = torch.meshgrid(
        torch.arange(height, device=K.device, dtype=K.dtype) + 0.5,
        torch.arange(width, device=K.device, dtype=K.dtype) + 0.5,
        indexing="ij",
    )
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], dim=-1)
    return rays / rays.norm(dim=-1, keepdim=True)


def _shade(
    blended: Tensor,
    alpha: Tensor,
    normal: Tensor,
    viewmat: Tensor,
    K: Tensor,
    light: DiffuseLight | None = None,
    fused: bool = True,
) -> tuple[Tensor, Tensor]:
    """Deferred shading of the alpha-blended albedo [H, W, 3] -> (premultiplied RGB, the albedo per unit alpha
    [H, W, 3]): the albedo lit by ``light`` (None: unlit), clipped at 1 before the alpha. For CPU tensors (and a
    fixed camera) the numba kernels of :mod:`.fused_shading` unless ``fused`` is False (the torch below, the
    reference)."""
    h, w = alpha.shape
    if fused and alpha.device.type == "cpu" and not viewmat.requires_grad:
        lit = (None, None) if light is None else (light.coefficients, light.camera)
        return shade_cpu(blended, alpha, normal, K, viewmat[:3, :3].T, *lit)
    diffuse = blended / alpha.clamp_min(ALPHA_FLOOR)[..., None]  # [H, W, 3]
    # only pixels some Gaussian reaches: elsewhere the colour is multiplied by an alpha of exactly 0 and no
    # Gaussian would receive its gradient (the same result, at the cost of the object's share of the image)
    drawn = torch.nonzero(alpha.reshape(-1) > 0)[:, 0]  # [P]
    rotation = viewmat[:3, :3].T  # camera -> world
    view = pixel_rays(K, w, h).reshape(-1, 3)[drawn] @ rotation.T  # [P, 3] world
    n = normal.reshape(-1, 3)[drawn] @ rotation.T
    shaded = shade_points(diffuse.reshape(-1, 3)[drawn], n, view, light)
    color = diffuse.new_zeros(h * w, 3).index_copy(0, drawn, shaded).reshape(h, w, 3)
    return color * alpha[..., None], diffuse


def shade_points(albedo: Tensor, normals: Tensor, views: Tensor, light: DiffuseLight | None = None) -> Tensor:
    """The colour [P, 3] of surface points [P] seen along unit world ``views`` [P, 3] with unit world
    ``normals`` [P, 3] (towards the viewer): the ``albedo`` [P, 3], lit by ``light`` where there is one, clipped
    at 1."""
    shaded = albedo if light is None else albedo * light.irradiance(normals, views)
    return shaded.clamp(max=1.0)
