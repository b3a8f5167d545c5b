"""``rasterization()``: gsplat's public rendering call, with torch / cpu / gsplat backends.

Same signature and return values as ``gsplat.rasterization`` for the arguments
tacsplat uses, so that gsplat itself is a drop-in backend on CUDA:

* ``torch``: pure-PyTorch reference (:mod:`.reference`), autograd backward; the oracle.
* ``cpu``: numba kernels with hand-written backward for projection + SH
  (:mod:`.cpu_project`) and tile compositing (:mod:`.cpu_composite`);
  float32 only. The torch projection is used instead for antialiased mode or
  when viewmats / Ks require gradients.
* ``gsplat``: the gsplat package, when CUDA and gsplat are present.
* ``auto``: gsplat for CUDA tensors when it is installed, else ``cpu`` for
  float32 and ``torch`` for float64 inputs.
"""

from __future__ import annotations

import importlib.util
import math
import numbers
from typing import Literal

import torch
from torch import Tensor

from tacsplat.errors import InvalidInputError
from tacsplat.reconstruction.raster.reference import (
    MAX_ALPHA,
    TRANSMITTANCE_THRESHOLD,
    Projection,
    project_gaussians,
    rasterize_to_pixels_torch,
)
from tacsplat.reconstruction.raster.spherical_harmonics import num_sh_bases, spherical_harmonics

RENDER_MODES = ("RGB", "D", "ED", "MD", "RGB+D", "RGB+ED", "RGB+MD")
BACKENDS = ("auto", "torch", "cpu", "gsplat")


def _check_tensor(name: str, value, shape: tuple, dtype=None, device=None) -> Tensor:
    """Validate one tensor argument: type, shape (None = any size), dtype (float32 or float64), device."""
    if not isinstance(value, Tensor):
        raise InvalidInputError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if value.dim() != len(shape) or any(s is not None and s != v for s, v in zip(shape, value.shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise InvalidInputError(f"{name} must have shape {want}, got {list(value.shape)}")
    if value.dtype not in (torch.float32, torch.float64):
        raise InvalidInputError(f"{name} must be a float32 or float64 tensor, got {value.dtype}")
    if dtype is not None and value.dtype != dtype:
        raise InvalidInputError(f"{name} has dtype {value.dtype} but means has {dtype}; use one dtype")
    if device is not None and value.device != device:
        raise InvalidInputError(f"{name} is on {value.device} but means is on {device}")
    return value


def _check_values(tensors: dict[str, Tensor], Ks: Tensor) -> None:
    """Every entry finite and every focal length positive, decided by one reduction and one wait for the
    device (a finite sum proves its entries finite); only a failing call looks closer, to name the culprit,
    and passes if there is none (finite entries whose sum overflows)."""
    sums = [t.detach().sum() for t in tensors.values() if t.numel()]
    finite = torch.isfinite(torch.stack(sums)).all() if sums else torch.tensor(True)
    focal = (Ks[:, 0, 0] > 0).all() & (Ks[:, 1, 1] > 0).all()
    if bool(finite & focal):
        return
    for name, value in tensors.items():
        if value.numel() and not bool(torch.isfinite(value).all()):
            bad = "NaN" if bool(torch.isnan(value).any()) else "infinite"
            raise InvalidInputError(f"{name} contains {bad} values")
    if not bool(focal):
        raise InvalidInputError("Ks must have positive focal lengths fx = K[0, 0] and fy = K[1, 1]")


def gsplat_available() -> bool:
    """Whether the gsplat backend can run here: CUDA and the gsplat package."""
    return torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None


def _choose_backend(backend: str, means: Tensor) -> str:
    if backend not in BACKENDS:
        raise InvalidInputError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "gsplat" and not gsplat_available():
        raise InvalidInputError("backend='gsplat' needs CUDA and the gsplat package")
    if backend == "cpu" and means.dtype != torch.float32:
        raise InvalidInputError(f"backend='cpu' computes in float32; means has dtype {means.dtype}")
    if backend != "auto":
        return backend
    if means.is_cuda and gsplat_available():
        return "gsplat"
    return "cpu" if means.dtype == torch.float32 and means.device.type == "cpu" else "torch"


def sh_colors(
    degree: int,
    means: Tensor,  # [N, 3]
    campos: Tensor,  # [3] camera centre
    coeffs: Tensor,  # [N, K, D] SH coefficients, K >= (degree + 1)^2
    backend: Literal["auto", "torch", "cpu", "gsplat"] = "auto",
) -> Tensor:
    """gsplat's SH colour max(SH(camera -> mean) + 0.5, 0) of every Gaussian -> [N, D], for a caller that
    composites its own channels: the fused numba kernel on the ``cpu`` backend (what ``rasterization``
    uses inside), :func:`.spherical_harmonics.spherical_harmonics` in torch otherwise or when the camera
    centre requires gradients."""
    if _choose_backend(backend, means) == "cpu" and not campos.requires_grad:
        from tacsplat.reconstruction.raster.cpu_project import sh_colors_cpu

        every = torch.ones(1, means.shape[0], 2, dtype=torch.int32, device=means.device)  # radii > 0: none culled
        return sh_colors_cpu(degree, means, campos[None], coeffs[:, : num_sh_bases(degree)].contiguous(), every)[0]
    return (spherical_harmonics(degree, means - campos, coeffs) + 0.5).clamp_min(0.0)


def rasterization(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz, unnormalised
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, D], [C, N, D] or SH coefficients [N, K, 3]
    viewmats: Tensor,  # [C, 4, 4] world-to-camera
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    packed: bool = False,
    tile_size: int = 16,
    backgrounds: Tensor | None = None,  # [C, D]
    render_mode: Literal["RGB", "D", "ED", "MD", "RGB+D", "RGB+ED", "RGB+MD"] = "RGB",
    rasterize_mode: Literal["classic", "antialiased"] = "classic",
    absgrad: bool = False,
    camera_model: str = "pinhole",
    backend: Literal["auto", "torch", "cpu", "gsplat"] = "auto",
    max_alpha: float = MAX_ALPHA,  # alpha clamp; gsplat's kernels fix it at 0.999, the default everywhere
) -> tuple[Tensor, Tensor, dict]:
    """Render C images of N Gaussians -> (render_colors [C, H, W, X], render_alphas [C, H, W, 1], meta).

    X is D for "RGB", 1 for "D"/"ED"/"MD" and D+1 for "RGB+D"/"RGB+ED"/"RGB+MD". "D" is the
    accumulated depth sum_i w_i z_i (the paper's depth render, Eq. 5), "ED" that sum
    divided by the alpha, "MD" the median depth: the depth of the Gaussian at which the
    accumulated transmittance first falls below 0.5, 0 where it never does (the paper's
    evaluation depth). "MD" is forward only (no loss needs its gradient); on the gsplat
    backend, which has no such mode, the "MD" modes are computed by the CPU backend. ``meta`` holds ``means2d`` [C, N, 2] (call
    ``retain_grad()`` on it before backward for densification), ``radii``
    [C, N, 2] int32 (0 = culled), ``depths`` [C, N], ``conics`` [C, N, 3],
    ``opacities`` [C, N], ``width``, ``height``, ``tile_size``, ``n_cameras``,
    ``backend``; the ``cpu`` backend adds ``n_intersections`` (tile-Gaussian
    pairs) and ``n_pairs`` (pixel-Gaussian pairs its forward pass evaluated),
    the ``cpu`` and ``torch`` backends ``median_depths`` [C, H, W, 1] (what
    "MD" renders, found by every pass: an evaluation needing both depths
    renders once).

    Degenerate Gaussians have one finite meaning on every backend: scales
    enter only through the covariance ``R diag(s^2) R^T`` (their sign does not
    matter; a zero scale is a point, widened by the ``eps2d`` pixel
    dilation), a zero quaternion is the identity rotation, opacities under
    1/255 (zero, negative) are culled and alphas are clamped at ``max_alpha``. A view
    where nothing is drawn (all culled, behind or at the camera, N = 0) is
    empty, with zero gradients for every input. Non-finite inputs, dtypes other
    than float32 and float64, zero cameras, non-positive focal lengths or image
    sizes, a negative or non-finite ``eps2d``, a NaN ``radius_clip`` and a
    ``max_alpha`` outside (0, 1 - 1e-4] raise :class:`InvalidInputError` naming
    the argument.
    """
    _check_tensor("means", means, (None, 3))
    n, dtype, device = means.shape[0], means.dtype, means.device
    _check_tensor("quats", quats, (n, 4), dtype, device)
    _check_tensor("scales", scales, (n, 3), dtype, device)
    _check_tensor("opacities", opacities, (n,), dtype, device)
    _check_tensor("viewmats", viewmats, (None, 4, 4), dtype, device)
    n_cams = viewmats.shape[0]
    if n_cams == 0:
        raise InvalidInputError("viewmats must hold at least one camera, got shape [0, 4, 4]")
    _check_tensor("Ks", Ks, (n_cams, 3, 3), dtype, device)
    if sh_degree is None:
        if not isinstance(colors, Tensor) or colors.dim() not in (2, 3):
            raise InvalidInputError("colors must be [N, D] or [C, N, D] when sh_degree is None")
        _check_tensor("colors", colors, (n, None) if colors.dim() == 2 else (n_cams, n, None), dtype, device)
    else:
        if not isinstance(sh_degree, int) or not 0 <= sh_degree <= 3:
            raise InvalidInputError(f"sh_degree must be None or an int in 0..3, got {sh_degree!r}")
        _check_tensor("colors", colors, (n, None, 3), dtype, device)
        if colors.shape[1] < num_sh_bases(sh_degree):
            raise InvalidInputError(
                f"colors has {colors.shape[1]} SH coefficients but sh_degree={sh_degree} needs "
                f"{num_sh_bases(sh_degree)}"
            )
    n_channels = colors.shape[-1]
    if backgrounds is not None:
        _check_tensor("backgrounds", backgrounds, (n_cams, n_channels), dtype, device)
    named = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmats=viewmats, Ks=Ks)
    _check_values(named if backgrounds is None else {**named, "backgrounds": backgrounds}, Ks)
    if not all(isinstance(v, numbers.Integral) and v >= 1 for v in (width, height)):
        raise InvalidInputError(f"width and height must be positive ints, got {width!r} x {height!r}")
    width, height = int(width), int(height)
    if render_mode not in RENDER_MODES:
        raise InvalidInputError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if rasterize_mode not in ("classic", "antialiased"):
        raise InvalidInputError(f"rasterize_mode must be 'classic' or 'antialiased', got {rasterize_mode!r}")
    if not (0.0 < near_plane < far_plane):
        raise InvalidInputError(f"need 0 < near_plane < far_plane, got {near_plane} and {far_plane}")
    if not (isinstance(tile_size, int) and tile_size >= 1):
        raise InvalidInputError(f"tile_size must be a positive int, got {tile_size!r}")
    if not (isinstance(eps2d, numbers.Real) and math.isfinite(eps2d) and eps2d >= 0.0):
        raise InvalidInputError(f"eps2d must be a finite number >= 0, got {eps2d!r}")
    if not (isinstance(radius_clip, numbers.Real) and not math.isnan(radius_clip)):
        raise InvalidInputError(f"radius_clip must be a number, got {radius_clip!r}")
    if not 0.0 < max_alpha <= 1.0 - TRANSMITTANCE_THRESHOLD:
        raise InvalidInputError(
            f"max_alpha must be in (0, {1.0 - TRANSMITTANCE_THRESHOLD:g}], got {max_alpha!r}: a pixel stops before "
            f"a Gaussian that would bring its transmittance to {TRANSMITTANCE_THRESHOLD:g} or below, so a larger "
            "alpha would leave an opaque Gaussian undrawn"
        )
    chosen = _choose_backend(backend, means)
    options = dict(
        near_plane=near_plane,
        far_plane=far_plane,
        radius_clip=radius_clip,
        eps2d=eps2d,
        sh_degree=sh_degree,
        tile_size=tile_size,
        render_mode=render_mode,
        rasterize_mode=rasterize_mode,
    )
    inputs = (means, quats, scales, opacities, colors, viewmats, Ks)
    if chosen == "gsplat" and render_mode in ("MD", "RGB+MD"):  # gsplat has no median depth: the CPU backend's
        cpu = [t.detach().float().cpu() for t in inputs]
        bgs = None if backgrounds is None else backgrounds.detach().float().cpu()
        out_colors, out_alphas, meta = rasterization(
            *cpu, width, height, **options, backgrounds=bgs, backend="cpu", max_alpha=max_alpha
        )
        return out_colors.to(means.device, dtype), out_alphas.to(means.device, dtype), meta
    if chosen == "gsplat":
        from tacsplat.reconstruction.raster.gsplat_backend import rasterization_gsplat

        if max_alpha != MAX_ALPHA:
            raise InvalidInputError(
                f"backend='gsplat' clamps alpha at {MAX_ALPHA} (fixed in its kernels), got max_alpha={max_alpha}"
            )
        return rasterization_gsplat(
            *inputs,
            width,
            height,
            **options,
            packed=packed,
            backgrounds=backgrounds,
            absgrad=absgrad,
            camera_model=camera_model,
        )
    if packed or absgrad or camera_model != "pinhole":
        raise InvalidInputError(
            f"backend {chosen!r} supports packed=False, absgrad=False and camera_model='pinhole' only"
        )

    n_bases = None if sh_degree is None else num_sh_bases(sh_degree)
    cameras_need_grad = viewmats.requires_grad or Ks.requires_grad
    camera = (viewmats, Ks, width, height, near_plane, far_plane, eps2d, radius_clip)
    if chosen == "cpu" and rasterize_mode == "classic" and not cameras_need_grad:
        # fused numba projection and SH with hand-written backward
        from tacsplat.reconstruction.raster.cpu_project import project_gaussians_cpu, sh_colors_cpu

        means2d, conics, depths, radii = project_gaussians_cpu(*inputs[:4], *camera)
        proj = Projection(means2d, conics, depths, radii, opacities.expand(n_cams, n))
        if sh_degree is not None:
            campos = torch.linalg.inv(viewmats.detach())[:, :3, 3]  # [C, 3]
            point_colors = sh_colors_cpu(sh_degree, means, campos, colors[:, :n_bases].contiguous(), radii)
    else:
        proj = project_gaussians(*inputs[:4], *camera, antialiased=rasterize_mode == "antialiased")
        if sh_degree is not None:
            campos = torch.linalg.inv(viewmats)[:, :3, 3]  # [C, 3]
            dirs = means[None, :, :] - campos[:, None, :]  # [C, N, 3]
            sh = spherical_harmonics(sh_degree, dirs, colors[None].expand(n_cams, -1, -1, -1))
            visible = (proj.radii > 0).all(dim=-1)[..., None]  # [C, N, 1]
            point_colors = torch.clamp_min(torch.where(visible, sh, torch.zeros_like(sh)) + 0.5, 0.0)
    if sh_degree is None:
        point_colors = colors.expand(n_cams, n, n_channels) if colors.dim() == 2 else colors

    bg = backgrounds
    if render_mode in ("D", "ED", "MD"):
        point_colors = proj.depths[..., None]
        bg = None
    elif render_mode in ("RGB+D", "RGB+ED", "RGB+MD"):
        point_colors = torch.cat([point_colors, proj.depths[..., None]], dim=-1)
        if bg is not None:
            bg = torch.cat([bg, torch.zeros_like(bg[:, :1])], dim=-1)

    args = (proj.means2d, proj.conics, point_colors, proj.opacities, proj.radii, proj.depths, width, height)
    if chosen == "cpu":
        from tacsplat.reconstruction.raster.cpu_composite import rasterize_to_pixels_cpu

        render_colors, render_alphas, stats, median = rasterize_to_pixels_cpu(*args, tile_size, bg, max_alpha)
        extra_meta = {"n_intersections": int(stats[0]), "n_pairs": int(stats[1]), "median_depths": median}
    else:
        render_colors, render_alphas, median = rasterize_to_pixels_torch(*args, tile_size, bg, max_alpha)
        extra_meta = {"median_depths": median}
    if render_mode in ("ED", "RGB+ED"):
        expected = render_colors[..., -1:] / render_alphas.clamp_min(1e-10)
        render_colors = torch.cat([render_colors[..., :-1], expected], dim=-1)
    elif render_mode in ("MD", "RGB+MD"):
        render_colors = torch.cat([render_colors[..., :-1], median], dim=-1)

    meta = {
        **vars(proj),  # means2d, conics, depths, radii, opacities
        "width": width,
        "height": height,
        "tile_size": tile_size,
        "n_cameras": n_cams,
        "tile_width": math.ceil(width / tile_size),  # gsplat's keys that its strategies read
        "tile_height": math.ceil(height / tile_size),
        "camera_ids": None,  # (packed mode only, as in gsplat)
        "gaussian_ids": None,
        "backend": chosen,
        **extra_meta,
    }
    return render_colors, render_alphas, meta
