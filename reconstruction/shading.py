"""What a view of the Gaussians looks like: colour, alpha, depth and normals from one rasterization pass.

:func:`render` is the one place the trainer and the evaluation turn Gaussians into images.
Its extra outputs ride in the same pass as extra colour channels:

* **normals** -- each Gaussian's normal is its shortest axis (:func:`gaussian_normals`),
  turned towards the camera and expressed in the camera frame; the pass blends them like
  colours, and the pixel normal is that sum normalised (2DGS / PGSR style);
* **appearance** -- ``"sh"``: the view-dependent colour of the SH coefficients (3DGS);
  ``"reflective"``: a deferred, reflection-aware shading (3DGS-DR / GaussianShader style):
  each Gaussian carries a diffuse colour (its SH DC band), a specular tint and a roughness;
  the pass blends them with the normals, and each pixel is shaded as
  ``diffuse + tint * L(reflect(view, normal), roughness)``, ``L`` a learned environment map
  (:class:`EnvironmentMap`) prefiltered by roughness. A reflection then no longer has to be
  painted as geometry behind the surface;
  ``"lit"``: "reflective" whose diffuse colour is an albedo times the irradiance of a learned distant
  light at the pixel's normal (:class:`DiffuseLight`), and whose colour saturates at 1 as a camera's
  does. Shading then has to come from the normals, which ties the colours of the views to the
  geometry even where a glossy surface has no texture;
  ``"sh-lit"``: the view-dependent SH colour as the albedo that light lights, saturating at 1 (no
  environment: the SH bands above the first keep the view-dependent part, highlights and reflections, as in
  3DGS);
* **plane depth** -- each Gaussian's distance from the camera to the plane it lies in (its normal through
  its mean), blended like a colour; with the blended normal it gives each pixel's depth as the hit of its
  ray with the blended plane, ``sum w d / <sum w n, ray>`` (PGSR's unbiased depth), where the centre depth
  of 3DGS gives each Gaussian one depth over its whole footprint.

Plain RGB(+depth) with SH goes straight through :func:`rasterization` (its fused SH path).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from tacsplat.reconstruction.config import LIT, SPECULAR, Appearance, DepthRender
from tacsplat.reconstruction.fused_normals import gaussian_normals_cpu
from tacsplat.reconstruction.fused_shading import ALPHA_FLOOR, TINY, shade_cpu
from tacsplat.reconstruction.gaussians import Gaussians, quats_to_rotmats, sh0_to_rgb
from tacsplat.reconstruction.raster import rendering as raster  # the module: tests spy on its calls
from tacsplat.reconstruction.raster.spherical_harmonics import SH_C0, sh_basis

REFLECTIVE_PARAMS = {"tint": 3, "roughness": 1}  # extra per-Gaussian parameters (logits) of "reflective" and "lit"


def add_reflective_params(gaussians: Gaussians) -> None:
    """Give every Gaussian a specular tint (logit -2: little specular) and a roughness (logit 0: 0.5)."""
    n, device = len(gaussians), gaussians.means.device
    gaussians.params["tint"] = torch.nn.Parameter(torch.full((n, 3), -2.0, device=device))
    gaussians.params["roughness"] = torch.nn.Parameter(torch.zeros((n, 1), device=device))


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


class EnvironmentMap(torch.nn.Module):
    """A learned equirectangular radiance map [3, H, 2H], prefiltered by roughness through a mip pyramid.

    ``lookup(directions, roughness)`` blends the pyramid levels nearest to ``roughness * (levels - 1)``
    (roughness 0: the full-resolution map, a mirror; 1: the coarsest, a diffuse average).
    """

    def __init__(self, height: int = 16, device=None):
        super().__init__()
        self.log_radiance = torch.nn.Parameter(torch.full((3, height, 2 * height), math.log(0.5), device=device))

    @property
    def levels(self) -> int:
        return int(math.log2(self.log_radiance.shape[1])) + 1

    def pyramid(self) -> list[Tensor]:
        level = torch.exp(self.log_radiance)[None]  # [1, 3, H, 2H]
        levels = [level]
        while level.shape[2] > 1:
            level = F.avg_pool2d(level, 2)
            levels.append(level)
        return levels

    def lookup(self, directions: Tensor, roughness: Tensor) -> Tensor:
        """Radiance [P, 3] along world ``directions`` [P, 3] (any length; zero: the horizon at azimuth 0) at
        ``roughness`` [P] in [0, 1]. Gradients stay finite everywhere, the zenith and nadir included."""
        squared = (directions * directions).sum(-1, keepdim=True)  # [P, 1]
        none = squared <= TINY
        unit = torch.where(none, directions.new_tensor([1.0, 0.0, 0.0]), directions)
        x, y, z = (unit / torch.sqrt(torch.where(none, 1.0, squared))).unbind(-1)
        flat = x * x + y * y
        pole = flat <= TINY  # straight up or down: any azimuth will do, and atan2's gradient there is 0/0
        u = torch.atan2(torch.where(pole, 0.0, y), torch.where(pole, 1.0, x)) / math.pi  # azimuth, world z up
        v = -torch.atan2(z, torch.sqrt(flat + TINY)) / (math.pi / 2)  # elevation: -1 zenith, +1 nadir
        grid = torch.stack([u, v], dim=-1)[None, :, None, :]  # [1, P, 1, 2]
        samples = torch.stack([F.grid_sample(level, grid, align_corners=False, padding_mode="border")[0, :, :, 0]
                               for level in self.pyramid()])  # [L, 3, P]
        position = roughness.clamp(0.0, 1.0) * (len(samples) - 1)  # [P]
        index = torch.arange(len(samples), device=directions.device, dtype=position.dtype)
        weights = (1.0 - (position[None, :] - index[:, None]).abs()).clamp_min(0.0)  # [L, P] tent
        return torch.einsum("lp,lcp->pc", weights, samples)


def equirect_directions(height: int, device=None) -> Tensor:
    """Unit world directions [H, 2H, 3] through the texel centres of an equirectangular map in
    :class:`EnvironmentMap`'s layout (the inverse of its lookup's mapping): zenith at the top row, azimuth from
    -180 degrees at the left."""
    v = (2 * torch.arange(height, device=device, dtype=torch.float64) + 1) / height - 1.0  # [H], -1 at the top
    u = (2 * torch.arange(2 * height, device=device, dtype=torch.float64) + 1) / (2 * height) - 1.0  # [2H]
    elevation, azimuth = torch.meshgrid(-v * (math.pi / 2), u * math.pi, indexing="ij")
    return torch.stack([elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin()], dim=-1)


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
    """How Gaussians are coloured: their ``appearance``, for "reflective" and "lit" the learned environment, and
    for "lit" and "sh-lit" the diffuse light (None: the albedo unlit)."""

    appearance: Appearance = "sh"
    environment: EnvironmentMap | None = None
    light: DiffuseLight | None = None
    depth: DepthRender = "centre"  # how its depth is rendered (TrainConfig.depth_render)


@dataclass
class RenderOutput:
    rgb: Tensor  # [H, W, 3] colour before the background (alpha-premultiplied)
    alpha: Tensor  # [H, W]
    depth: Tensor | None  # [H, W] accumulated ("D") or expected ("ED") depth
    normal: Tensor | None  # [H, W, 3] unit camera-frame normal towards the camera (0 where nothing is drawn)
    meta: dict
    albedo: Tensor | None = None  # [H, W, 3] the blended diffuse colour per unit alpha (all but "sh")


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
    environment: EnvironmentMap | None = None,
    light: DiffuseLight | None = None,  # "lit", "sh-lit": the diffuse light (None: unlit, the albedo)
    world_normals: Tensor | None = None,  # [N, 3] gaussian_normals(g.quats, g.scales), when the caller has them
    depth_render: DepthRender = "centre",  # with depth_mode: each Gaussian's centre depth, or the ray's hit with the
    # blended plane ("plane"; renders the normals too)
) -> RenderOutput:
    """Render one view; see the module docstring for what each option adds to the pass. A caller that also needs
    the Gaussians' normals (a loss) computes them once and passes them as ``world_normals``."""
    g = gaussians
    plane = depth_mode is not None and depth_render == "plane"
    if not normals and appearance == "sh" and not plane:
        mode = "RGB" if depth_mode is None else f"RGB+{depth_mode}"
        colors, alphas, meta = raster.rasterization(
            g.means, g.quats, g.scales, g.opacities, g.sh_coefficients(sh_degree), viewmat, K, width, height,
            sh_degree=sh_degree, render_mode=mode, backend=backend,
        )  # fmt: skip
        depth = None if depth_mode is None else colors[0, ..., 3]
        return RenderOutput(colors[0, ..., :3], alphas[0, ..., 0], depth, None, meta)

    campos = -viewmat[0, :3, :3].T @ viewmat[0, :3, 3]  # [3]
    to_gaussian = g.means - campos  # [N, 3]
    if appearance in ("sh", "sh-lit"):
        features = raster.sh_colors(sh_degree, g.means, campos, g.sh_coefficients(sh_degree), backend)
    else:
        features = torch.cat([sh0_to_rgb(g.params["sh0"][:, 0]).clamp_min(0.0), torch.sigmoid(g.params["tint"]),
                              torch.sigmoid(g.params["roughness"])], dim=-1)  # [N, 7]
    channels = [features]
    with_normals = normals or appearance != "sh" or plane
    if with_normals:
        n = gaussian_normals(g.quats, g.scales, fused_kernels(backend)) if world_normals is None else world_normals
        n = torch.where(((n * to_gaussian).sum(-1, keepdim=True) > 0), -n, n)  # towards the camera
        channels.append(n @ viewmat[0, :3, :3].T)  # camera frame
    if plane:
        channels.append((n * to_gaussian).sum(-1, keepdim=True))  # [N, 1] <n, mu - c>: minus the plane's distance
    mode = "RGB" if depth_mode is None else f"RGB+{depth_mode}"
    colors, alphas, meta = raster.rasterization(
        g.means, g.quats, g.scales, g.opacities, torch.cat(channels, dim=-1)[None], viewmat, K, width, height,
        render_mode=mode, backend=backend,
    )  # fmt: skip
    out, alpha = colors[0], alphas[0, ..., 0]
    depth = None if depth_mode is None else out[..., -1]
    normal = None
    if with_normals:
        summed = out[..., features.shape[1] : features.shape[1] + 3]
        normal = F.normalize(summed, dim=-1, eps=1e-8)
    if plane:
        blended = out[..., features.shape[1] : features.shape[1] + 4]  # [H, W, 4] sum w n, sum w <n, mu - c>
        hit, meets = plane_hit_depth(blended[..., :3], blended[..., 3], K[0])
        depth = torch.where(meets, hit if depth_mode == "ED" else hit * alpha, depth)  # else the centre depth
    if appearance == "sh":
        return RenderOutput(out[..., :3], alpha, depth, normal, meta)
    rgb, albedo = _shade(out[..., : features.shape[1]], alpha, normal, viewmat[0], K[0],
                         environment if appearance in SPECULAR else None, light if appearance in LIT else None,
                         saturate=appearance in LIT, fused=fused_kernels(backend))
    return RenderOutput(rgb, alpha, depth, normal, meta, albedo)


PLANE_MIN_COS = 0.1  # plane depth: a pixel whose blended plane faces its ray less (grazing, or facing away, or
# no plane: nothing drawn) keeps the centre depth


def plane_hit_depth(normal_sum: Tensor, offset_sum: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """The depth [H, W] at which each pixel's ray meets its blended plane {x : <N, x> = O} (camera frame, x from
    the camera centre), N = ``normal_sum`` [H, W, 3] = sum w n (normals towards the camera) and O = ``offset_sum``
    [H, W] = sum w <n, mu - c>: both sums carry the same weights, so the plane is their blend. Also [H, W] bool
    where that depth holds: the cosine between the plane's normal and the reversed ray is at least PLANE_MIN_COS
    (elsewhere the depth is a finite placeholder with finite gradients)."""
    height, width = offset_sum.shape
    unit = pixel_rays(K, width, height)  # [H, W, 3]
    facing = (normal_sum * unit).sum(-1)  # [H, W] <sum w n, unit ray>, negative where the plane faces the camera
    meets = -facing >= PLANE_MIN_COS * normal_sum.norm(dim=-1).clamp_min(TINY)
    along = facing / unit[..., 2]  # <sum w n, ray at depth 1>
    return offset_sum / torch.where(meets, along, -torch.ones_like(along)), meets


def pixel_rays(K: Tensor, width: int, height: int) -> Tensor:
    """Unit camera-frame ray directions [H, W, 3] through the pixel centres (+0.5)."""
    v, u = torch.meshgrid(torch.arange(height, device=K.device, dtype=K.dtype) + 0.5,
                          torch.arange(width, device=K.device, dtype=K.dtype) + 0.5, indexing="ij")
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], dim=-1)
    return rays / rays.norm(dim=-1, keepdim=True)


def _shade(blended: Tensor, alpha: Tensor, normal: Tensor, viewmat: Tensor, K: Tensor,
           environment: EnvironmentMap | None, light: DiffuseLight | None = None, saturate: bool = False,
           fused: bool = True) -> tuple[Tensor, Tensor]:
    """Deferred shading of alpha-blended [H, W, 7] (diffuse, tint, roughness; [H, W, 3] diffuse only without an
    ``environment``) -> (premultiplied RGB, the diffuse colour per unit alpha [H, W, 3]); with a ``light`` the
    diffuse colour is an albedo it lights; ``saturate``: colours clipped at 1 before the alpha. For CPU tensors
    (and a fixed camera) the numba kernels of :mod:`.fused_shading` unless ``fused`` is False (the torch below,
    the reference)."""
    h, w = alpha.shape
    if fused and alpha.device.type == "cpu" and not viewmat.requires_grad:
        return shade_cpu(blended, alpha, normal, K, viewmat[:3, :3].T,
                         None if environment is None else environment.log_radiance,
                         None if light is None else light.coefficients, None if light is None else light.camera,
                         saturate)
    diffuse = blended[..., :3] / alpha.clamp_min(ALPHA_FLOOR)[..., None]  # [H, W, 3]
    # only pixels some Gaussian reaches: elsewhere the colour is multiplied by an alpha of exactly 0 and no
    # Gaussian would receive its gradient (the same result, at the cost of the object's share of the image)
    drawn = torch.nonzero(alpha.reshape(-1) > 0)[:, 0]  # [P]
    rotation = viewmat[:3, :3].T  # camera -> world
    view = pixel_rays(K, w, h).reshape(-1, 3)[drawn] @ rotation.T  # [P, 3] world
    n = normal.reshape(-1, 3)[drawn] @ rotation.T
    tint = roughness = None
    if environment is not None:
        drawn_alpha = alpha.reshape(-1, 1)[drawn].clamp_min(ALPHA_FLOOR)  # [P, 1]
        drawn_blended = blended.reshape(-1, blended.shape[-1])[drawn]  # [P, 7]
        tint, roughness = drawn_blended[:, 3:6] / drawn_alpha, drawn_blended[:, 6] / drawn_alpha[:, 0]
    shaded = shade_points(diffuse.reshape(-1, 3)[drawn], n, view, light, environment, tint, roughness, saturate)
    colour = diffuse.new_zeros(h * w, 3).index_copy(0, drawn, shaded).reshape(h, w, 3)
    return colour * alpha[..., None], diffuse


def shade_points(albedo: Tensor, normals: Tensor, views: Tensor, light: DiffuseLight | None = None,
                 environment: EnvironmentMap | None = None, tint: Tensor | None = None,
                 roughness: Tensor | None = None, saturate: bool = False) -> Tensor:
    """The colour [P, 3] of surface points [P] seen along unit world ``views`` [P, 3] with unit world
    ``normals`` [P, 3] (towards the viewer): the diffuse colour ``albedo`` [P, 3], lit by ``light`` where there
    is one, plus the specular ``tint`` [P, 3] times the ``environment``'s radiance along the reflected view at
    ``roughness`` [P] where there is one; clipped at 1 if ``saturate``."""
    shaded = albedo if light is None else albedo * light.irradiance(normals, views)
    if environment is not None:
        reflected = views - 2.0 * (views * normals).sum(-1, keepdim=True) * normals
        shaded = shaded + tint * environment.lookup(reflected, roughness)  # [P, 3]
    return shaded.clamp(max=1.0) if saturate else shaded
